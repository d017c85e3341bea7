"""`bb-align soak` in miniature: a real service process flooded over Zenoh on loopback by simulated peers with
valid frames and attacks; every message must be accounted for (the full run's numbers are in docs/security.md)."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from bb_align.cli import app
from bb_align.lab.flood import FloodConfig
from bb_align.lab.soak import ATTACKS, run_soak
from bb_align.lab.soak_phases import FloodPhase


def test_short_soak_accounts_for_every_message(tmp_path):
    report = run_soak(
        duration_s=6.0,
        warmup_s=2.0,
        n_peers=2,
        frames=2,
        attack_share=0.4,
        rss_growth_mb=150,
        oversized_every_s=3.0,
        log_dir=tmp_path,
        progress=False,
    )
    assert report["ok"], json.dumps(report["checks"])
    assert all(
        report["checks"][k]
        for k in (
            "no_crash",
            "exit_code_0_on_sigterm",
            "every_valid_frame_answered_or_counted",
            "every_valid_frame_accepted_or_dropped_at_intake",
            "every_result_received",
            "every_attack_refused_with_the_right_error",
        )
    )
    sent = report["sent"]
    assert sent["valid_peer"] > 0 and sent["attacks"] > 0 and set(sent["by_kind"]) & set(ATTACKS)
    # every attack refused, no valid frame; a PNG bomb (well formed, signed by the car) is refused when a worker
    # decodes it, or replaced unread by the car's next frame (counted as dropped, never answered with a pose)
    service = report["service"]
    assert service["refused_at_decode"] + service["not_decoded"] == sent["by_kind"].get("png_bomb", 0)
    assert service["rejected_total"] == sent["attacks"] - service["not_decoded"]
    assert service["outcomes"].get("invalid_frame", 0) == service["refused_at_decode"]
    assert report["service"]["results_received"] > 0 and report["latency_ms"]["p50"] > 0
    assert report["service"]["peers_tracked_end"] <= 3  # junk sender ids never became peers
    # signed attacks (replays, NaN boxes, PNG bombs, spoofed ids) are told to their sender; junk never is
    notices = report["service"]["refusal_notices"]
    assert (
        set(notices) <= {"replayed", "invalid", "forbidden"} and report["checks"]["no_refusal_notice_for_unsigned_junk"]
    )
    signed_attacks = sum(sent["by_kind"].get(k, 0) for k in ("replay", "nan_box", "png_bomb", "spoofed_id"))
    assert (sum(notices.values()) > 0) == (signed_attacks > 0)
    assert report["rss_mb"]["start"] > 50 and report["exit_code"] == 0


def test_a_short_keyless_flood_charges_no_signed_id_and_results_keep_flowing(tmp_path):
    """The flood phase in miniature: the ego and one peer stream signed frames (Ed25519, bb-align keys) at 10 Hz
    while a keyless process floods both their frame keys (1-byte junk, zero-MAC and forged envelopes, unsigned,
    replays of their own frames); the same length without the flood before it."""
    flooder = FloodConfig(small_per_cycle=50, big_bytes=64 * 1024, replays_per_cycle=5)
    report = run_soak(
        duration_s=1.0,
        warmup_s=1.0,
        n_peers=1,
        frames=2,
        attack_share=0.0,
        flood=FloodPhase(seconds=4.0, blocks=1, lead_s=0.5, flooder=flooder),
        log_dir=tmp_path,
        progress=False,
    )
    flood, baseline = report["phases"]["flood"], report["phases"]["baseline"]
    fl = flood["flooder"]
    assert fl["total_messages"] > 1000 and fl["messages"]["replay"] > 0, fl  # the flood ran, replays included
    assert sum(flood["refused_at_the_door"].values()) > 1000  # ... and reached the service: refused at its door
    assert flood["refused_at_the_door"].get("replayed", 0) > 0
    for name, phase in (("baseline", baseline), ("flood", flood)):
        # Every signed frame passed the gate. One in a few thousand used to vanish under the flood: the door's batch
        # loop dropped a message whenever a batch was full (docs/security.md, Floods; fixed, the door now takes one
        # message at a time). 30 runs of this test at load 8-13 lost none of 4 800 signed frames.
        assert phase["ego"]["lost"] == 0 and phase["peers"]["lost"] == 0, (name, phase)
        assert phase["intake_dropped_charged_to_signed_ids"] == 0 and phase["per_peer"]["car1"]["intake_dropped"] == 0
    assert flood["results"] > 0  # results keep flowing under the flood
    assert report["checks"]["flood_junk_never_charged_to_a_signed_id"]
    assert report["checks"]["no_crash"] and report["exit_code"] == 0
    assert report["config"]["signing"].startswith("ed25519")


def test_soak_refuses_non_loopback_targets():
    out = CliRunner().invoke(
        app, ["soak", "--connect", "tcp/10.0.0.1:7447", "--rest", "http://10.0.0.1:8000", "--key", "k" * 32]
    )
    assert out.exit_code != 0 and "loopback" in out.output
