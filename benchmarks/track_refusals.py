"""Why the tracker refuses frames whose answer is in fact right: the offline filter of
benchmarks/track_calibration.py (the tracker re-run on the recorded measurements of `bb-align track --records`)
with every frame's verdict kept, tallied by the rule that refused it and by distance.

    python benchmarks/track_refusals.py docs/tracking/records_seed11.jsonl [--set '{"evidence_sigmas": 2.5}']

A frame counts from its sequence's first valid answer on (as `bb-align track` scores). "right": the track's pose
within 1 m and 1 deg of the truth, valid or not; "refused right": right but not valid, by why_not's rule.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bb_align.engine.config import TrackConfig  # noqa: E402
from bb_align.engine.geometry import pose_error, se2  # noqa: E402
from bb_align.engine.tracker import PeerTrack  # noqa: E402
from track_calibration import _measurement, _sequences  # noqa: E402

BINS = ((0, 40), (40, 70), (70, 1e9))
RULES = (
    ("bound: yaw", r"bounds the answer's error by [0-9.]+ m / ([0-9.]+) deg"),
    ("outside measurement", r"outside this frame's measurement"),
    ("track uncertainty", r"track's uncertainty exceeds"),
    ("support", r"found [0-9.]+ of the peer"),
    ("no refinement", r"no refinement"),
)


def rule_of(a, cfg: TrackConfig) -> str:
    """The rule that refused a frame: the evidence bound split into its translation and yaw parts."""
    why = a.why_not or ""
    m = re.search(r"bounds the answer's error by ([0-9.]+) m / ([0-9.]+) deg", why)
    if m:
        t, r = float(m.group(1)), float(m.group(2))
        return "bound: " + "+".join(
            k for k, bad in (("m", t > cfg.evidence_bound_m), ("deg", r > cfg.evidence_bound_deg)) if bad
        )
    for name, pat in RULES[1:]:
        if re.search(pat, why):
            return name
    if a.source == "prediction":
        return "refinement failed (prediction only)"
    if a.source == "acquisition":
        return "acquisition failed or refused"
    return f"other: {a.source} {why[:40]}"


def tally(seqs, cfg: TrackConfig) -> dict:
    out = {b: Counter() for b in BINS}
    for recs in seqs.values():
        track, started = PeerTrack(cfg), False
        for r in recs:
            m = _measurement(r, cfg.measurement_inflation, cfg)
            O = r["odometry"]
            O_e, O_p = (se2(*O[0]), se2(*O[1])) if O else (None, None)
            a = track.step(r["stamp"], lambda T_pred, m=m: m, lambda T_prior, m=m: m, O_e, O_p)
            started |= a.valid
            if not started:
                continue
            b = next(b for b in BINS if b[0] <= r["distance_m"] < b[1])
            right = a.T_ego_peer is not None and max(np.array(pose_error(a.T_ego_peer, se2(*r["truth"])))) <= 1.0
            out[b]["frames"] += 1
            if a.valid:
                out[b]["valid right" if right else "valid WRONG"] += 1
            elif right:
                out[b]["refused right: " + rule_of(a, cfg)] += 1
            else:
                out[b]["refused, not right"] += 1
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("records", nargs="+")
    ap.add_argument("--set", default="{}", help="TrackConfig overrides as JSON")
    args = ap.parse_args()
    cfg = TrackConfig(**json.loads(args.set))
    for b, c in tally(_sequences(args.records), cfg).items():
        n = c.pop("frames", 0)
        print(f"distance {b[0]:g}-{b[1]:g} m: {n} frames")
        for k, v in sorted(c.items(), key=lambda kv: -kv[1]):
            print(f"  {k:45s} {v:5d}  {100 * v / max(n, 1):5.1f} %")


if __name__ == "__main__":
    main()
