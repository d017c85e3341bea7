"""`bb-align soak` in miniature: a real service process flooded over Zenoh on loopback by simulated peers with
valid frames and attacks; every message must be accounted for (the full run's numbers are in docs/security.md)."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from bb_align.cli import app
from bb_align.lab.soak import ATTACKS, run_soak


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
    assert report["service"]["rejected_total"] == sent["attacks"]  # every attack refused, no valid frame
    assert report["service"]["results_received"] > 0 and report["latency_ms"]["p50"] > 0
    assert report["service"]["peers_tracked_end"] <= 3  # junk sender ids never became peers
    # signed attacks (replays, NaN boxes, PNG bombs, spoofed ids) are told to their sender; junk never is
    notices = report["service"]["refusal_notices"]
    assert set(notices) <= {"replayed", "invalid"} and report["checks"]["no_refusal_notice_for_unsigned_junk"]
    signed_attacks = sum(sent["by_kind"].get(k, 0) for k in ("replay", "nan_box", "png_bomb", "spoofed_id"))
    assert (sum(notices.values()) > 0) == (signed_attacks > 0)
    assert report["rss_mb"]["start"] > 50 and report["exit_code"] == 0


def test_soak_refuses_non_loopback_targets():
    out = CliRunner().invoke(
        app, ["soak", "--connect", "tcp/10.0.0.1:7447", "--rest", "http://10.0.0.1:8000", "--key", "k" * 32]
    )
    assert out.exit_code != 0 and "loopback" in out.output
