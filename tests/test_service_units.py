"""Latest-only queues, request bounds, fair order, the ego cache's nearest-in-time choice, replay passes and
refusal notices."""

from __future__ import annotations

import threading
import time
from collections import Counter

import numpy as np

from bb_align.protocol import BevMeta, Frame, Limits, WireError, pack
from bb_align.server.cache import EgoCache
from bb_align.server.peers import PeerTable
from bb_align.server.refusals import RefusalNotices
from bb_align.server.scheduler import Job, Scheduler


def _job(sender, n, reply=None):
    return Job(sender, time.perf_counter(), "test", data=bytes([n]), reply=reply)


def test_latest_only_keeps_the_newest_and_reports_each_drop():
    s = Scheduler(depth=1)
    assert s.put_frame(_job("car1", 0)) is None
    dropped = [s.put_frame(_job("car1", n)) for n in range(1, 5)]
    assert [d.data[0] for d in dropped] == [0, 1, 2, 3]
    job = s.get(0)
    assert job.data == bytes([4]) and s.get(0) is None


def test_depth_two_keeps_the_two_newest_in_order():
    s = Scheduler(depth=2)
    drops = [s.put_frame(_job("car1", n)) for n in range(4)]
    assert [d.data[0] for d in drops if d] == [0, 1]
    first = s.get(0)
    assert first.data[0] == 2 and s.get(0) is None  # car1 is busy until done()
    s.done(first)
    assert s.get(0).data[0] == 3


def test_senders_take_turns_and_requests_get_their_turn():
    s = Scheduler(depth=1, max_requests=2)
    s.put_frame(_job("car1", 1))
    s.put_frame(_job("car2", 2))
    assert s.put_request(_job("", 9, reply=lambda _: None)) and s.put_request(_job("", 8, reply=lambda _: None))
    assert not s.put_request(_job("", 7, reply=lambda _: None))  # bounded
    order = []
    while (job := s.get(0)) is not None:
        order.append(job.data[0])
        s.done(job)
    assert order == [1, 2, 9, 8]


def test_close_wakes_workers_and_returns_waiting_jobs():
    s = Scheduler()
    got = []
    t = threading.Thread(target=lambda: got.append(s.get(10)))
    t.start()
    s.put_request(_job("", 1, reply=lambda _: None))
    t.join(5)
    s.put_request(_job("", 2, reply=lambda _: None))
    left = s.close()
    assert got[0].data[0] == 1 and [j.data[0] for j in left] == [2]
    assert s.get(0) is None and not s.put_request(_job("", 3, reply=lambda _: None))


def _ego(stamp, seq):
    return Frame(vehicle_id="ego", seq=seq, stamp=stamp, png=b"", bev=BevMeta(resolution_m=0.4, range_m=20))


def test_cache_returns_nearest_in_time_and_keeps_the_last_k():
    cache = EgoCache(size=3)
    assert cache.nearest(1.0) is None
    for seq, stamp in enumerate([1.0, 1.1, 1.2, 1.3]):
        cache.add(_ego(stamp, seq), bev=None)
    assert cache.stamps() == [1.1, 1.2, 1.3] and len(cache) == 3
    assert cache.nearest(1.16).frame.seq == 2
    assert cache.nearest(0.5).frame.seq == 1  # 1.0 was evicted
    assert cache.nearest(9.0).frame.seq == 3
    cache.add(_ego(1.3, 4), bev=None)
    assert cache.nearest(1.3).frame.seq == 4  # equally near: the newer frame
    assert cache.prepared() == 0


def test_cache_wait_for_waits_for_the_ego_frame_of_the_sweep_not_an_older_one():
    cache = EgoCache(size=3)
    cache.add(_ego(1.0, 0), bev=None)
    assert cache.wait_for(1.01, 0.02, timeout=5.0)  # the sweep's frame is there: no wait
    t0 = time.perf_counter()
    # The frame of 1.0 s is within any usual skew of 1.1 s, but a whole sweep older: the wait goes on (bounded).
    assert not cache.wait_for(1.1, 0.02, timeout=0.2)
    assert 0.15 <= time.perf_counter() - t0 < 2.0
    landing = threading.Timer(0.1, lambda: cache.add(_ego(1.1, 1), bev=None))
    landing.start()
    t0 = time.perf_counter()
    assert cache.wait_for(1.1, 0.02, timeout=5.0)  # the sweep's ego frame lands 0.1 s later: woken by it
    assert time.perf_counter() - t0 < 2.0
    landing.join()


def test_cache_wait_for_does_not_wait_for_a_later_sweep_of_an_unsynchronised_ego():
    """Ego frames every 0.1 s (1.0, 1.1, 1.2). A peer swept 25 ms after the ego's newest frame: the ego's next frame
    (due at 1.3) is of a later sweep, so no wait at all (the newest, 25 ms away, is the nearest there is). A peer
    swept 10 ms before the ego's next frame, or with it (phase-locked): that frame is the peer's sweep's, so the wait
    goes on until it lands."""

    def every_100_ms():
        cache = EgoCache(size=5)
        for k in range(3):
            cache.add(_ego(1.0 + 0.1 * k, k), bev=None)
        return cache

    t0 = time.perf_counter()
    assert not every_100_ms().wait_for(1.225, 0.02, timeout=5.0)
    assert time.perf_counter() - t0 < 0.05
    for peer_stamp in (1.29, 1.3):
        cache = every_100_ms()
        landing = threading.Timer(0.1, lambda cache=cache: cache.add(_ego(1.3, 3), bev=None))
        landing.start()
        t0 = time.perf_counter()
        assert cache.wait_for(peer_stamp, 0.02, timeout=5.0)  # woken by the ego frame of 1.3 s
        assert 0.05 <= time.perf_counter() - t0 < 2.0
        landing.join()


def test_entry_features_are_computed_once_for_concurrent_users():
    cache = EgoCache(size=2)
    entry = cache.add(_ego(1.0, 0), bev=None)
    calls, started = [], threading.Event()

    def prepare(e):
        calls.append(e.frame.seq)
        started.set()
        time.sleep(0.2)
        return "features"

    out = []
    threads = [threading.Thread(target=lambda: out.append(entry.features(prepare))) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(5)
    assert out == ["features"] * 3 and calls == [0] and cache.prepared() == 1


def test_the_ego_features_job_does_not_wait_for_a_worker_already_computing_them():
    """A peer frame's worker computing an ego frame's features holds them; the ego_features job for the same frame
    (wait=False) returns at once instead of blocking the other worker (8 peers: ~8 % of the workers' time)."""
    cache = EgoCache(size=2)
    entry = cache.add(_ego(1.0, 0), bev=None)
    started, release = threading.Event(), threading.Event()

    def prepare(e):
        started.set()
        release.wait(5)
        return "features"

    computing = threading.Thread(target=lambda: entry.features(prepare))
    computing.start()
    assert started.wait(5)
    t0 = time.perf_counter()
    assert entry.features(prepare, wait=False) is None and time.perf_counter() - t0 < 0.5
    release.set()
    computing.join(5)
    assert entry.features(prepare, wait=False) == "features" and entry.ready


def test_run_parts_runs_the_first_part_on_the_caller_and_keeps_the_order():
    """The engine's pool is shared by the service's workers: the caller works on its first part itself (rather than
    waiting idle while its parts queue behind another caller's), and the results come back in the parts' order."""
    from bb_align.engine.parallel import run_parts

    caller = threading.get_ident()
    ran: dict[int, int] = {}

    def part(i):
        ran[i] = threading.get_ident()
        time.sleep(0.01)
        return i * i

    assert run_parts(part, [3, 4, 5]) == [9, 16, 25]
    assert ran[3] == caller and ran[4] != caller and ran[5] != caller


def test_priority_sender_goes_first_without_reordering_the_rest():
    s = Scheduler(depth=1, priority=frozenset({"ego"}))
    for sender in ("car1", "car2", "ego"):
        s.put_frame(_job(sender, 0))
    order = []
    while (job := s.get(0)) is not None:
        order.append(job.sender)
        s.done(job)
    assert order == ["ego", "car1", "car2"]


def test_background_jobs_run_at_most_max_background_at_once_and_never_hold_back_streams():
    s = Scheduler(depth=1, background_prefix="@bg:", max_background=1)
    for sender in ("@bg:car1", "@bg:car2", "car1", "car2"):
        s.put_frame(_job(sender, 0))
    first = s.get(timeout=0)
    assert first.sender == "@bg:car1"  # in readiness order, while none runs
    # One background job runs: the other waits even though it is next in line; the streams go past it.
    assert [s.get(timeout=0).sender for _ in range(2)] == ["car1", "car2"]
    assert s.get(timeout=0) is None  # only @bg:car2 is ready, and it must wait
    s.done(first)
    assert s.get(timeout=0).sender == "@bg:car2"


def test_relative_prior_takes_roll_pitch_tz_of_the_reported_poses():
    from scipy.spatial.transform import Rotation

    from bb_align.protocol import Pose
    from bb_align.server.core import relative_prior

    ego_pose = Pose(x=10, y=5, z=1.9, roll=0.02, pitch=-0.01, yaw=0.4)
    peer_pose = Pose(x=30, y=9, z=2.3, roll=-0.03, pitch=0.05, yaw=0.9)

    def T(p):  # independent: scipy's intrinsic z-y'-x'' Euler angles
        out = np.eye(4)
        out[:3, :3] = Rotation.from_euler("ZYX", [p.yaw, p.pitch, p.roll]).as_matrix()
        out[:3, 3] = (p.x, p.y, p.z)
        return out

    T_rel = np.linalg.inv(T(ego_pose)) @ T(peer_pose)
    yaw, pitch, roll = Rotation.from_matrix(T_rel[:3, :3]).as_euler("ZYX")
    tz, r, p = relative_prior(
        _ego(0, 0).model_copy(update={"pose": ego_pose}), _ego(0, 0).model_copy(update={"pose": peer_pose})
    )
    np.testing.assert_allclose([tz, r, p], [T_rel[2, 3], roll, pitch], atol=1e-12)
    assert relative_prior(_ego(0, 0), _ego(0, 0)) is None


def test_nearest_ready_entry_within_the_skew():
    from bb_align.server.cache import EgoCache

    cache = EgoCache(5)
    entries = [cache.add(_ego(0.1 * i, i), None) for i in range(4)]
    assert cache.nearest_ready(0.31, 0.15) is None  # nothing prepared yet
    entries[1].features(lambda e: "features-1")
    entries[2].features(lambda e: "features-2")
    assert cache.nearest_ready(0.31, 0.15) is entries[2]
    assert cache.nearest_ready(0.05, 0.15) is entries[1]
    assert cache.nearest_ready(0.9, 0.15) is None  # the prepared ones are too far in time


def test_wait_until_ready_reports_an_early_exit_and_a_timeout(tmp_path):
    import subprocess
    import sys

    import pytest

    from bb_align.lab.harness import wait_until_ready

    log = tmp_path / "child.log"
    log.write_text("boom: settings invalid\n")
    dead = subprocess.Popen([sys.executable, "-c", "raise SystemExit(3)"])
    dead.wait(10)
    with pytest.raises(RuntimeError, match=r"exited with code 3: boom"):
        wait_until_ready(dead, "http://127.0.0.1:9", 5.0, log, stop=lambda: None)
    mute = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    stopped = []
    try:
        with pytest.raises(RuntimeError, match="not ready within 0.5 s"):
            wait_until_ready(mute, "http://127.0.0.1:9", 0.5, log, stop=lambda: stopped.append(mute.kill()))
    finally:
        mute.kill()
        mute.wait(10)
    assert stopped, "the timeout stops the child"


# ---- issue 14: the replay profile's passes, and which refusals are told to their sender -----------------------
def _frame(vid, stamp, seq):
    return Frame(vehicle_id=vid, seq=seq, stamp=stamp, png=b"", bev=BevMeta(resolution_m=0.4, range_m=20))


def _admit_all(table, frames):
    out = []
    for f in frames:
        try:
            out.append("new pass" if table.admit(f, "frames") else "ok")
        except WireError as e:
            out.append(e.error)
    return out


def test_a_recording_played_again_is_a_new_pass_only_in_the_replay_profile():
    recording = [_frame("car1", 100.0 + 0.1 * k, k) for k in range(3)]
    normal = PeerTable(8, 60.0, reserved="ego", refuse_replays=True)
    assert _admit_all(normal, recording * 2) == ["ok"] * 3 + ["replayed"] * 3
    replay = PeerTable(8, 60.0, reserved="ego", refuse_replays=True, new_pass_on_rewind=True)
    assert _admit_all(replay, recording * 2) == ["ok", "ok", "ok", "new pass", "ok", "ok"]
    assert _admit_all(replay, [_frame("car1", 100.3, 3)]) == ["ok"]  # the pass goes on
    assert _admit_all(replay, [_frame("car1", 100.3, 3)]) == ["new pass"]  # never refused as a replay here
    assert replay.statuses()["car1"].sequence_restarts == 2


def test_an_ego_restart_drops_the_previous_pass_from_the_cache():
    cache = EgoCache(size=5)
    for seq, stamp in enumerate([10.0, 10.1, 10.2]):
        cache.add(_ego(stamp, seq), bev=None)
    assert cache.rewind(10.05) == 2 and cache.stamps() == [10.0]
    cache.add(_ego(10.05, 3), bev=None)
    assert cache.nearest(10.2).frame.seq == 3


def test_only_signed_stream_frames_are_told_why_and_at_a_bounded_rate():
    clock = [0.0]
    notices = RefusalNotices("ego", min_interval_s=0.1, max_tracked=2, clock=lambda: clock[0])
    e = WireError(422, "invalid", "stamp too old", "stamp", 30.0, "BBALIGN_LIMITS__MAX_STAMP_AGE_S")
    frame = pack(_frame("car1", 5.0, 7))

    def job(sender="car1", signer="fleet", reply=None):
        return Job(sender, 0.0, "zenoh", data=frame, reply=reply, meta={"signer": signer} if signer else {})

    n = notices.notice(job(), e, Limits())
    assert (n.peer_id, n.peer_seq, n.peer_stamp, n.status) == ("car1", 7, 5.0, 422)
    assert n.refused.setting == "BBALIGN_LIMITS__MAX_STAMP_AGE_S" and n.ego_id == "ego"
    assert notices.notice(job(signer=None), e, Limits()) is None  # no valid signature: no answer
    assert notices.notice(job(reply=lambda _: None), e, Limits()) is None  # queries get their own error reply
    assert notices.notice(job(), e, Limits()) is None  # again within 0.1 s
    assert notices.notice(job("car2"), e, Limits()) is not None
    assert notices.notice(job("car3"), e, Limits()) is None  # two senders within the interval: bounded
    clock[0] = 0.2
    assert notices.notice(job(), e, Limits()) is not None and notices.notice(job("car3"), e, Limits()) is not None
    garbled = Job("car1", 0.0, "zenoh", data=b"\xc1", meta={"signer": "fleet"})
    clock[0] = 1.0
    assert notices.notice(garbled, e, Limits()).peer_seq is None  # told, even when its seq cannot be read


def test_a_senders_results_leave_in_order_even_when_publishing_is_slow():
    """Two workers, one sender: the sender's next frame runs only after the previous result was published, so a
    slow publish (a busy link) cannot let the next frame's result overtake it."""
    from bb_align.protocol import Result
    from bb_align.server.core import AlignService
    from bb_align.server.settings import Settings

    svc = AlignService(Settings(profile="demo", workers=2, zenoh={"enabled": False}))
    svc._run = lambda job: Result(
        ego_id="ego", peer_id=job.sender, peer_seq=job.data[0], peer_stamp=0.0, success=False, reason="test"
    )
    published, first_started = [], threading.Event()

    def publish(res):
        if res.peer_seq == 1:
            first_started.set()
            time.sleep(0.3)  # the first result is slow to leave
        published.append(res.peer_seq)

    svc.publishers.append(publish)
    workers = [threading.Thread(target=svc._work, daemon=True) for _ in range(2)]
    for w in workers:
        w.start()
    try:
        svc.scheduler.put_frame(_job("car1", 1))
        assert first_started.wait(10)
        svc.scheduler.put_frame(_job("car1", 2))  # a worker is free: it may not take car1's frame yet
        deadline = time.monotonic() + 10
        while len(published) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        svc.scheduler.close()
        for w in workers:
            w.join(10)
    assert published == [1, 2]


def test_the_schedule_serves_tracked_frames_beside_acquisitions_fairly_and_drops_stale_frames_before_work():
    """Issue 47/45: with 16 peers the service's results fell 31 -> 4 a second: acquisitions took every worker, the
    tracked peers' frames waited behind them until their tracks ran out, and every frame became an acquisition.
    The schedule (no timing here, a fake clock): heavy jobs (acquisitions) use at most all workers but one while
    a peer is tracked, every worker while none is; tracked frames go past waiting acquisitions; peers take turns
    (latest frame wins); a frame that waited too long is dropped before any work."""
    now = [100.0]
    acquiring = {"a1", "a2", "a3"}
    tracked = [True]
    expired = []
    s = Scheduler(
        depth=1,
        heavy=lambda key: key in acquiring,
        light_expected=lambda: tracked[0],
        workers=2,
        max_background=1,
        max_wait_s=1.0,
        on_expired=expired.append,
        clock=lambda: now[0],
    )
    job = lambda sender, n: Job(sender, now[0], "test", data=bytes([n]))  # noqa: E731
    for sender in ("a1", "a2", "t1", "a3", "t2"):
        s.put_frame(job(sender, 0))
    first = s.get(0)
    assert first.sender == "a1"  # in turn: an acquisition while none runs
    light = [s.get(0) for _ in range(2)]
    assert [j.sender for j in light] == ["t1", "t2"]  # past a2 and a3: one worker for tracked frames
    assert s.get(0) is None  # only acquisitions are ready, and one runs
    s.put_frame(job("t1", 1))
    assert s.get(0) is None  # t1 is busy (its frames in order)
    s.done(light[0])
    assert s.get(0).data == bytes([1])  # t1's newer frame, still before a2
    s.done(first)
    assert s.get(0).sender == "a2"
    # Nobody tracked yet (a fleet starting up): acquisitions take every worker.
    tracked[0] = False
    assert s.get(0).sender == "a3"
    # Latest frame wins, and a frame that waited past max_wait_s is dropped before work.
    s2 = Scheduler(depth=1, max_wait_s=1.0, on_expired=expired.append, clock=lambda: now[0])
    assert s2.put_frame(job("t9", 1)) is None and s2.put_frame(job("t9", 2)).data == bytes([1])
    now[0] += 1.5
    assert s2.get(0) is None and [j.data for j in expired] == [bytes([2])] and s2.pending() == 0
    s2.put_frame(job("t9", 3))
    assert s2.get(0).data == bytes([3])
    # Fair shares: four tracked peers sending continuously, each frame taking 10 ms: each gets the same turns.
    s3 = Scheduler(depth=1, clock=lambda: now[0])
    served = Counter()
    for sender in ("p1", "p2", "p3", "p4"):
        s3.put_frame(job(sender, 0))
    for k in range(40):
        j = s3.get(0)
        served[j.sender] += 1
        s3.put_frame(job(j.sender, k % 200))  # its next frame arrived meanwhile
        now[0] += 0.01
        s3.done(j)
    assert set(served.values()) == {10}


def test_overdue_tracked_frames_go_before_fresh_ones_in_the_fair_order():
    """Unsynchronised peers at capacity: car "busy" has used the most of the workers lately, so in the fair order
    its frame waits behind every newer frame of the others, until its own next frame pushes it out (dropped). With
    ``overdue_s`` (the service's unmeasured_after_s: such a frame is answered in a few ms from its track's stream)
    light frames that waited longer take the light frames' turn before fresh ones, in the fair order among them
    (a sweep's frames become overdue together: by age they would always go in the order the cars published), while
    an acquisition (heavy, here the oldest) keeps its own turn; without ``overdue_s`` the fair order stands."""
    now = [10.0]
    job = lambda sender, t: Job(sender, t, "test", data=b"x")  # noqa: E731

    def schedule(overdue_s):
        s = Scheduler(depth=1, heavy=lambda key: key == "acq", clock=lambda: now[0], overdue_s=overdue_s)
        s._charge("busy", 1.0)  # the most of the workers' time lately
        s.put_frame(job("acq", 9.80))  # the oldest, but an acquisition
        s.put_frame(job("busy", 9.90))
        s.put_frame(job("late", 9.93))
        s.put_frame(job("fresh", 9.99))
        return s

    s = schedule(0.05)
    assert [s.get(0).sender for _ in range(4)] == ["acq", "late", "busy", "fresh"]
    s = schedule(None)
    assert [s.get(0).sender for _ in range(4)] == ["acq", "late", "fresh", "busy"]


def _cross_check_schedule():
    """A scheduler with a background share of 0.25 on 2 workers, its bucket full (0.5 worker-seconds, fake clock)."""
    now = [0.0]
    s = Scheduler(depth=1, background_prefix="@bg:", max_background=1, workers=2, background_share=0.25,
                  clock=lambda: now[0])  # fmt: skip
    now[0] = 1.0  # the bucket fills over the first second
    return s, now, lambda sender: Job(sender, now[0], "test")


def test_cross_checks_yield_to_waiting_tracked_frames_once_their_share_is_spent():
    """Cross-checks (one per track every few seconds, each a full acquisition) grow with the tracks: unbounded, 16
    peers' cross-checks took a worker from the tracked frames. Past ``background_share`` of the workers' time they
    let waiting tracked frames go first; with nothing else waiting they still run (fake clock, no timing)."""
    s, now, job = _cross_check_schedule()
    s.put_frame(job("@bg:car1"))
    s.put_frame(job("car2"))
    bg = s.get(0)
    assert bg.sender == "@bg:car1"  # its turn, within the share
    now[0] += 0.8  # a 0.8 s cross-check: the bucket (full at 0.5 worker-seconds) is charged 0.8, spent
    s.done(bg)
    assert s.get(0).sender == "car2"
    for sender in ("@bg:car3", "car4"):
        s.put_frame(job(sender))
    assert s.get(0).sender == "car4"  # the tracked frame goes past the waiting cross-check
    assert s.get(0).sender == "@bg:car3"  # nothing else waits: it runs anyway


def test_a_cross_check_is_charged_its_cpu_not_its_wall_time():
    """A cross-check runs its acquisition on both cores: 0.2 s of wall time may be 0.35 s of CPU. The share is
    of the workers' CPU, so it is charged what the worker measured (``Job.cpu_s``)."""
    s, now, job = _cross_check_schedule()
    s.put_frame(job("@bg:car1"))
    bg = s.get(0)
    now[0] += 0.2  # 0.2 s of wall time would leave 0.3 in the bucket ...
    bg.cpu_s = 0.55  # ... but it used 0.55 s of CPU: spent
    s.done(bg)
    for sender in ("@bg:car3", "car4"):
        s.put_frame(job(sender))
    assert s.get(0).sender == "car4"  # the tracked frame goes first: the share is spent


def test_a_cars_burst_of_requests_costs_its_own_latency_not_another_cars():
    """Issue 47: 8 threads posting one car's frames to /v1/align took 54 % of the engine (one FIFO of requests,
    one round-robin turn per request) and the other cars kept 0.61-0.63 of their results. Now requests wait per
    car, a car's requests run one at a time, and a worker takes the ready car that had the least of the workers'
    time lately (a fake clock: each job takes 50 ms); a full queue pushes out the burst's newest, not another
    car's request."""
    now = [0.0]
    pushed_out: list[Job] = []
    s = Scheduler(depth=1, max_requests=8, clock=lambda: now[0], on_pushed_out=pushed_out.append)
    req = lambda sender, n: Job(sender, now[0], "rest", data=bytes([n]), reply=lambda _: None)  # noqa: E731
    for n in range(8):  # car3's burst fills the request queues
        assert s.put_request(req("car3", n))
    assert s.put_request(req("car1", 100))  # full: car1's request pushes out the burst's newest ...
    assert [j.data[0] for j in pushed_out] == [7] and not s.put_request(req("car3", 8))  # ... car3 holds the most
    two = [s.get(0), s.get(0)]  # two workers
    assert [(j.sender, j.data[0]) for j in two] == [("car3", 0), ("car1", 100)]  # car3's requests: one at a time
    assert s.get(0) is None
    now[0] += 0.05
    for j in two:
        s.done(j)
    now[0] += 0.01
    s.put_frame(Job("car2", now[0], "zenoh", data=bytes([200])))  # a car's stream frame comes in after the burst
    order, held = [], []
    while len(order) < 7:
        job = s.get(0)
        if job is None:  # a worker is free but car3's next request waits: car1, car2 had far less time lately
            held.append(now[0])
            now[0] += 0.1
            continue
        order.append((job.sender, job.data[0]))
        now[0] += 0.05
        s.done(job)
    # car2's frame goes before the rest of car3's burst (car3 had its 50 ms of the workers lately, car2 none)
    assert order == [("car2", 200)] + [("car3", n) for n in range(1, 7)]
    # past 0.2 s more than the other cars active in the last second, car3's requests waited (held) until those
    # cars had been idle for a second; frames are never held
    assert held and s.usage("car3") > s.usage("car2") > 0.0
    s.put_request(req("car3", 9))
    s.put_frame(Job("car2", now[0], "zenoh", data=bytes([201])))
    assert s.get(0).sender == "car2"


def test_a_car_is_charged_the_cpu_its_jobs_used_engine_threads_included():
    """Issue 47: an acquisition keeps both cores busy (its parallel parts run on the engine's pool) while a tracked
    frame mostly uses one, so wall time undercharges the car whose every request is an acquisition. A job's
    ``cpu_s`` (what the worker measured) is charged instead of its wall time; ``metered`` counts the pool parts'
    CPU beside the calling thread's, checked against each part's own thread CPU."""
    import time as _time

    from bb_align.engine.parallel import metered, run_parts

    now = [0.0]
    s = Scheduler(clock=lambda: now[0], half_life_s=1e9)
    s.put_frame(Job("car1", 0.0, "zenoh", data=b"x"))
    job = s.get(0)
    now[0] += 0.05  # 50 ms of wall time ...
    job.cpu_s = 0.09  # ... in which the job used 90 ms of CPU on two threads
    s.done(job)
    assert abs(s.usage("car1") - 0.09) < 1e-12

    own: list[float] = []

    def busy(_):
        t0 = _time.thread_time()
        while _time.thread_time() - t0 < 0.03:
            pass
        own.append(_time.thread_time() - t0)

    with metered() as cpu:
        run_parts(busy, [0, 1])
    assert len(own) == 2 and cpu.seconds >= sum(own) - 1e-3  # the caller waited; its parts did the work
    with metered() as idle:
        _time.sleep(0.03)
    assert idle.seconds < 0.01  # waiting is not use


def test_the_tracks_hear_every_frames_odometry_and_the_next_step_checks_each_step():
    # A busy service steps car1's frames 0, 1 and then 9 (2-8 replaced unread). Its odometry re-anchors by 3 m at
    # frame 5, and frame 9 continues the motion after it: only the heard frames between tell the jump.
    from bb_align.engine.config import AlignConfig
    from bb_align.engine.geometry import ground_se2, se2, se3_from_se2
    from bb_align.engine.pipeline import Aligner
    from bb_align.server.tracks import PeerTracks

    def pose(k, jump=0.0):  # 15 m/s along x, 10 Hz, 4x4 as the wire's odometry
        return se3_from_se2(se2(0.0, 1.5 * k + jump, 0.0))

    tracks = PeerTracks(Aligner(AlignConfig()), max_tracks=4)
    for k in range(12):  # heard in arrival order; frames 10-11 are newer than the step and must not count
        tracks.hear("ego", k * 0.1, pose(k), ego=True)
        tracks.hear("car1", k * 0.1, pose(k, 3.0 if k >= 5 else 0.0), ego=False)
        tracks.hear("car2", k * 0.1, pose(k), ego=False)
    for car, jump_m in (("car1", 3.0), ("car2", 0.0)):
        track = tracks.get(car)
        watch = track.follower.track.odometry
        for k in (0, 1):  # the two frames stepped before
            watch.record({"ego": (k * 0.1, ground_se2(pose(k))), "peer": (k * 0.1, ground_se2(pose(k)))})
        track.observe(tracks.ego_heard, 0.9, 0.9)
        now = {"ego": (0.9, ground_se2(pose(9))), "peer": (0.9, ground_se2(pose(9, jump_m)))}
        jump, unchecked_m = watch.check(now)
        if jump_m:
            assert jump is not None and jump[0] == "peer" and "jumped" in jump[1], jump
        else:
            assert jump is None and unchecked_m < 0.5, (jump, unchecked_m)  # judged as one 0.1 s step
    tracks.clear()
    assert tracks.ego_heard.before(10.0) == []
