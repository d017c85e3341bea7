"""Keyless floods from several Zenoh sessions cannot starve a signed car (issue 31, F7).

The cause, measured (benchmarks/zenoh_rx_starvation.py, docs/security.md, Floods): a sample waiting for a place
in the door's full FIFO holds the Zenoh receive thread of its session's link, and Zenoh had 2; two flooding
sessions left no thread to read the cars' links, so their frames never reached any code of ours. Now the service
takes at most ``limits.zenoh_max_sessions`` sessions and gives Zenoh one receive thread more. The service runs in
its own process (the receive threads are set when a process opens its first Zenoh session), as it does deployed.
"""

from __future__ import annotations

import time

import httpx
import pytest

from bb_align.lab.flood import FloodConfig, FloodProcess
from bb_align.lab.harness import start_service
from bb_align_client import ZenohPeer, encode_frame
from service_support import FLEET_KEY, RANGE_M, moving_pair, secure_settings, wait_for

N_FRAMES = 15
PERIOD_S = 0.2


def test_two_keyless_flood_sessions_cannot_starve_a_signed_car(tmp_path):
    """Two flooders, each its own process and session, put 1-byte junk on the ego's and car1's frame keys as fast
    as their blocking publishers go (before the fix: car1 and the ego lost most of their frames). car1 publishes
    with the client's default publisher (congestion control DROP). Every frame it and the ego sent is accepted
    (one may be lost on the air), and its stream is answered up to its newest frame. How many of its frames the
    engine answers is the machine's pace, not the flood's: measured by benchmarks/stream_flood.py."""
    settings = secure_settings(workers=2)
    frames = moving_pair(N_FRAMES)
    config = FloodConfig(
        duration_s=1.0 + PERIOD_S * N_FRAMES + 1.0, small_per_cycle=200, big_per_cycle=0, replays_per_cycle=0
    )
    svc = start_service(settings, FLEET_KEY, tmp_path, timeout_s=300)
    try:
        ep = [svc.zenoh_endpoint]
        with (
            ZenohPeer("ego", connect=ep, key=FLEET_KEY, verify_answers=False) as ego_car,
            ZenohPeer("car1", connect=ep, key=FLEET_KEY) as car1,
        ):
            poses = car1.poses("ego")
            assert ego_car.wait_for_subscriber(10) and car1.wait_for_subscriber(10)
            time.sleep(0.2)  # the pose subscription reaches the service
            flooders = [FloodProcess(ep[0], settings.zenoh.prefix, {"ego": None, "car1": None}, config) for _ in "ab"]
            try:
                for f in flooders:
                    f.start()
                time.sleep(1.0)  # both floods are running before the first real frame
                t0 = time.monotonic()
                for k, (_, ego, peer) in enumerate(frames):
                    t = time.time()
                    ego_car.publish(_enc(ego, "ego", k, t))
                    car1.publish(_enc(peer, "car1", k, t))
                    time.sleep(max(0.0, t0 + (k + 1) * PERIOD_S - time.monotonic()))
                flooded = [f.finish() for f in flooders]
            finally:
                for f in flooders:
                    f.stop()
            assert all(f["total_messages"] > 10_000 for f in flooded), flooded  # both floods ran at full speed
            wait_for(
                lambda: svc.get("/v1/peers").get("car1", {}).get("frames_accepted", 0) >= N_FRAMES - 1,
                timeout=20,
                what=f"car1's frames accepted under the flood (of {N_FRAMES})",
            )
            got = []
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                try:
                    got.append(poses.get(timeout=max(0.1, deadline - time.monotonic())))
                except TimeoutError:
                    break
                if got[-1].peer_seq == N_FRAMES - 1:
                    break
            status = svc.get("/v1/peers")["car1"]
            ego_frames = _ego_frames_received(svc)
    finally:
        exit_code = svc.stop()
    assert exit_code == 0
    # every accepted frame answered or counted as dropped (latest-only: the engine's pace is the machine's), the
    # newest answered, and none of the answers wanted for an ego frame
    assert status["results"] + status["frames_dropped"] == status["frames_accepted"], status
    assert got and got[-1].peer_seq == N_FRAMES - 1, ([r.peer_seq for r in got], status)
    assert [r.peer_seq for r in got] == sorted(r.peer_seq for r in got)
    assert not any(r.reason == "stale_ego_frame" for r in got), [r.reason for r in got]
    assert ego_frames >= N_FRAMES - 1, ego_frames


def _enc(cloud, vehicle_id: str, seq: int, stamp: float) -> bytes:
    return encode_frame(cloud.points, cloud.boxes, vehicle_id=vehicle_id, stamp=stamp, seq=seq, range_m=RANGE_M)


def _ego_frames_received(svc) -> float:
    text = httpx.get(svc.rest + "/metrics", timeout=10).text
    want = 'bbalign_frames_received_total{door="zenoh",kind="ego"} '
    return sum(float(ln.rsplit(" ", 1)[1]) for ln in text.splitlines() if ln.startswith(want))


def test_forged_frames_carry_the_copied_certificate_a_fresh_stamp_and_a_bad_signature(tmp_path):
    """The probes of issue 47 (benchmarks/door_probes.py) send 1 MB envelopes shaped like frames: the genuine
    certificate given, a frame payload with a fresh stamp and a seq far ahead, and a zero or a random signature
    that does not verify under the certificate's key; paced kinds are due at their rate."""
    import msgpack
    from cryptography.exceptions import InvalidSignature
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

    from bb_align.lab.flood import _due, big_junk
    from bb_align.lab.harness import make_credentials
    from bb_align.protocol import Limits, peek_signed
    from bb_align.protocol.identity import Certificate

    cert = make_credentials(tmp_path, ["car1"])["car1"].certificate_bytes
    public = Ed25519PublicKey.from_public_bytes(Certificate.from_bytes(cert).public_key)
    sigs = set()
    for kind in ("forged_frame", "forged_frame_random_sig", "forged_frame_random_sig"):
        env = peek_signed(big_junk(kind, "car2", 1 << 20, cert), Limits())
        body = msgpack.unpackb(env.payload, raw=False)
        assert (env.key_id, env.alg, env.cert) == ("car2", "ed25519", cert) and len(env.mac) == 64
        assert abs(body["stamp"] - time.time()) < 5 and body["seq"] == 1 << 62 and len(body["png"]) == 1 << 20
        with pytest.raises(InvalidSignature):
            public.verify(env.mac, env.payload)
        sigs.add(env.mac)
    assert len(sigs) == 3 and b"\0" * 64 in sigs
    t0 = time.perf_counter()
    assert _due(t0, 0, 3.0) and not _due(t0, 3, 3.0) and _due(t0, 10**6, 0.0)
