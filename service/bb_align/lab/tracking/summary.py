"""The tracking replay's summary: accuracy by distance, wrong answers, the covariance's honesty, lock losses and
the time per tracked and per acquired frame.

Accuracy counts every frame from a sequence's first valid answer on (before it, nothing is tracked yet): a frame is
under 1 m & 1 deg when it was answered as valid within both. A wrong frame was answered as valid but off by more.
"""

from __future__ import annotations

import math

import numpy as np

from bb_align.lab.evaluation.runner import DIST_BUCKETS

WITHIN_70M = ("0-20", "20-40", "40-70")


def _bucket(d: float) -> str:
    return next(k for k, (lo, hi) in DIST_BUCKETS.items() if lo <= d < hi)


def _good(r: dict, max_m: float, max_deg: float) -> bool:
    return r["success"] and r["t_err_m"] <= max_m and r["r_err_deg"] <= max_deg


def _frac(n: int, d: int) -> float | None:
    return n / d if d else None


def _pct(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def after_first_answer(records: list[dict]) -> list[dict]:
    """Each sequence's frames from its first valid answer on."""
    out, started = [], set()
    for r in records:
        if r["success"]:
            started.add(r["sequence"])
        if r["sequence"] in started:
            out.append(r)
    return out


def _accuracy(rows: list[dict], max_m: float, max_deg: float) -> dict:
    good = sum(_good(r, max_m, max_deg) for r in rows)
    answered = sum(r["success"] for r in rows)
    return {
        "frames": len(rows),
        "frac_under_1m_1deg": _frac(good, len(rows)),
        "frac_answered": _frac(answered, len(rows)),
        "wrong_frames": answered - good,
    }


def summarize(records: list[dict], max_m: float = 1.0, max_deg: float = 1.0) -> dict:
    tracked = after_first_answer(records)
    sequences = sorted({r["sequence"] for r in records})
    overall = _accuracy(tracked, max_m, max_deg)
    by_distance = {
        k: _accuracy([r for r in tracked if _bucket(r["distance_m"]) == k], max_m, max_deg) for k in DIST_BUCKETS
    }
    within = _accuracy([r for r in tracked if _bucket(r["distance_m"]) in WITHIN_70M], max_m, max_deg)
    answered = [r for r in records if r["success"] and r["within_3sigma"] is not None]
    first = {}
    for r in records:
        first.setdefault(r["sequence"], r["stamp"])
    acquired_at = {}
    for r in records:
        if r["success"] and r["sequence"] not in acquired_at:
            acquired_at[r["sequence"]] = r["stamp"] - first[r["sequence"]]
    # a tracked frame's time: frames the engine stepped (not those answered unmeasured, --unmeasured-every)
    tracked_ms = [
        r["ms"] for r in records if not r["ran_acquisition"] and r["source"] != "none" and not r.get("unmeasured")
    ]
    acquire_ms = [r["ms"] for r in records if r["ran_acquisition"]]
    return {
        "sequences": len(sequences),
        "frames": len(records),
        "frames_after_first_answer": overall["frames"],
        "frac_under_1m_1deg": overall["frac_under_1m_1deg"],
        "frac_answered": overall["frac_answered"],
        "within_70m": within,
        "by_distance": by_distance,
        "wrong_frames": overall["wrong_frames"],
        "wrong_frames_frac": _frac(overall["wrong_frames"], overall["frames"]),
        "frac_within_3sigma": _frac(sum(r["within_3sigma"] for r in answered), len(answered)),
        "sequences_never_answered": len(sequences) - len(acquired_at),
        "acquire_s_median": float(np.median(list(acquired_at.values()))) if acquired_at else math.inf,
        "lock_losses": sum(1 for r in records if (r["event"] or "").startswith("lost")),
        "acquisitions": len(acquire_ms),
        "tracked_ms_p50": _pct(tracked_ms, 50),
        "tracked_ms_p99": _pct(tracked_ms, 99),
        "acquire_ms_p50": _pct(acquire_ms, 50),
        "ego_frame_ms_p50": _pct([r["ego_frame_ms"] for r in records], 50),
        "by_source": {
            s: sum(r["source"] == s for r in tracked)
            for s in ("acquisition", "tracking", "stream", "prediction", "none")
        },
    }


def format_summary(s: dict) -> str:
    def pct(v):
        return "   -  " if v is None else f"{100 * v:5.1f}%"

    lines = [
        f"{s['sequences']} sequences, {s['frames']} frames ({s['frames_after_first_answer']} after the first answer)",
        f"under 1 m & 1 deg {pct(s['frac_under_1m_1deg'])}   within 70 m {pct(s['within_70m']['frac_under_1m_1deg'])}"
        f"   wrong {pct(s['wrong_frames_frac'])} ({s['wrong_frames']})   true error within 3 sigma "
        f"{pct(s['frac_within_3sigma'])}",
        "distance   frames  <1m&1deg  answered",
    ]
    for k, b in s["by_distance"].items():
        lines.append(f"{k:>8} m {b['frames']:6d}   {pct(b['frac_under_1m_1deg'])}    {pct(b['frac_answered'])}")
    ms = lambda v: "-" if v is None else f"{v:.1f}"
    lines.append(
        f"first answer after {s['acquire_s_median']:.1f} s (median), {s['lock_losses']} lock losses, "
        f"{s['acquisitions']} acquisitions; tracked frame {ms(s['tracked_ms_p50'])} ms p50 "
        f"({ms(s['tracked_ms_p99'])} p99), acquisition {ms(s['acquire_ms_p50'])} ms p50; "
        f"per ego frame {ms(s['ego_frame_ms_p50'])} ms p50 (its refinement cloud, shared by every peer)"
    )
    return "\n".join(lines)


def answers_summary(records: list[dict]) -> dict:
    """A run without the truth (a bag with no reference topics): how many frames were answered, and why the others
    were refused."""
    refused: dict[str, int] = {}
    for r in records:
        if not r["success"]:
            refused[r["reason"] or "none"] = refused.get(r["reason"] or "none", 0) + 1
    first = next((r["stamp"] - records[0]["stamp"] for r in records if r["success"]), None)
    return {
        "frames": len(records),
        "successful": sum(r["success"] for r in records),
        "refused": dict(sorted(refused.items())),
        "first_answer_after_s": first,
        "acquisitions": sum(r["ran_acquisition"] for r in records),
        "lock_losses": sum(1 for r in records if (r["event"] or "").startswith("lost")),
    }


def format_answers(s: dict) -> str:
    refused = ", ".join(f"{k}: {v}" for k, v in s["refused"].items()) or "none"
    first = "never" if s["first_answer_after_s"] is None else f"after {s['first_answer_after_s']:.1f} s"
    return (
        f"{s['frames']} frames, {s['successful']} successful (no reference poses: not scored); refused {refused}; "
        f"first answer {first}; {s['acquisitions']} acquisitions, {s['lock_losses']} lock losses"
    )
