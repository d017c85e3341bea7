"""The simulated sweeps replayed through a real service (not only through the engine's follower): a short swept
sequence (`bb-align sim --sweep`'s writer: odometry with drift and GNSS-grade reported poses in each yaml) sent
frame by frame to a real uvicorn service on loopback (REST /v1/align, the ego frame inline, tracking on), every
successful answer checked against the simulator's truth. The full sweeps: benchmarks/track_through_service.py."""

from __future__ import annotations

import httpx
import pytest

from bb_align.engine.config import AlignConfig, BevConfig
from bb_align.lab.sim.sweep import write_sweep
from bb_align.lab.tracking.summary import summarize
from bb_align.lab.tracking.through_service import replay_through_service, wrong_answers
from service_support import RANGE_M, running_service, service_settings

FRAMES = 10


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    root = tmp_path_factory.mktemp("sweep")
    write_sweep(root, seed=5, index=0, frames=FRAMES)  # receding: the cars start ~5 m apart
    return root


@pytest.mark.parametrize("odometry", [True, False], ids=["odometry", "no_odometry"])
def test_a_swept_sequence_through_the_service_is_never_answered_wrongly(sweep, odometry):
    settings = service_settings(zenoh=False, align=AlignConfig(bev=BevConfig(range_m=RANGE_M)))
    with running_service(settings) as (_, url), httpx.Client(base_url=url, timeout=120) as http:
        records = replay_through_service(http, sweep, odometry=odometry, bev={"range_m": RANGE_M})
    assert len(records) == FRAMES
    assert wrong_answers(records) == []
    s = summarize(records)
    assert s["sequences_never_answered"] == 0
    # Within 20 m the refinement bounds its answers well: most frames after the first answer are answered right.
    assert s["frac_under_1m_1deg"] >= 0.7, [(r["frame"], r["source"], r["reason"], r["notes"]) for r in records]
    assert [r["source"] for r in records].count("tracking") >= FRAMES // 2
