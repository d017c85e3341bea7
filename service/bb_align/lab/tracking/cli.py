"""`bb-align track`: replay swept two-car sequences through the follower the service runs; summary and figures."""

from __future__ import annotations

import json
from itertools import islice
from pathlib import Path

import typer

from bb_align.io.defaults import DESKEW_DEFAULT, DESKEW_HELP


def register(app: typer.Typer) -> None:
    @app.command("track")
    def track_cmd(
        root: Path = typer.Argument(
            ...,
            exists=True,
            help="sequences (e.g. `bb-align sim --sweep`), or a ROS 2 bag: a rosbag2 folder or .mcap / .db3 file",
        ),
        json_out: Path | None = typer.Option(None, "--json", help="write the summary JSON here"),
        plots: Path | None = typer.Option(None, "--plots", file_okay=False, help="write PNG figures here"),
        records_out: Path | None = typer.Option(None, "--records", help="write every frame's record (JSON lines)"),
        odometry: bool = typer.Option(True, "--odometry/--no-odometry", help="fuse the yaml's odometry_pose"),
        gnss: bool = typer.Option(True, "--gnss/--no-gnss", help="the yaml's gnss_pose as the acquisitions' prior"),
        deskew: bool = typer.Option(DESKEW_DEFAULT, "--deskew/--no-deskew", help=DESKEW_HELP),
        limit: int | None = typer.Option(None, "--limit", min=1, help="replay at most this many sequences"),
        max_frames: int | None = typer.Option(None, "--frames", min=1, help="only the first frames of each"),
        workers: int = typer.Option(2, "--workers", min=1, help="processes (one sequence each)"),
        config: Path | None = typer.Option(None, "--config", help="an AlignConfig as JSON or YAML (track: .track)"),
        unmeasured_every: int | None = typer.Option(
            None,
            "--unmeasured-every",
            min=2,
            help="answer every N-th frame from the track's stream without measuring it, when the track can (as a "
            "busy service does: unmeasured_after_s); default: every frame measured",
        ),
        topic: list[str] = typer.Option(
            [],
            "--topic",
            metavar="KEY=TOPIC",
            help="a bag's topic for KEY (repeatable): ego_points, peer_points, ego_odometry, peer_odometry, "
            "ego_gnss, peer_gnss, ego_heading, peer_heading, ego_reference, peer_reference (empty TOPIC: not "
            "used), or max_skew_s=SECONDS (docs/rosbag.md)",
        ),
        through_service: bool = typer.Option(
            False,
            "--through-service",
            help="send the frames to a real `bb-align serve` started for the run (loopback, REST, the same config) "
            "as the cars would, instead of the engine in this process",
        ),
        bag_out: Path | None = typer.Option(
            None,
            "--bag-out",
            help="write the answers as a rosbag2 with MCAP storage here (a new folder; several sequences: one "
            "bag each under it): /tf, the pose with covariance, the verdicts, the BV images (docs/rosbag.md)",
        ),
    ) -> None:
        """Replay every sequence under ROOT, or a ROS 2 bag of two cars (docs/rosbag.md), frame by frame through the
        engine's tracker (acquire, then refine from the prediction and fuse) and measure it against the truth:
        accuracy by distance, wrong answers, whether the 3-sigma bound holds the true error, lock losses, time per
        tracked and per acquired frame (a bag without reference poses: answered and refused frames)."""
        from bb_align.io.config_file import load_align_config
        from bb_align.io.dataset import find_scenarios, iter_scenario_frames
        from bb_align.io.rosbag import is_bag, read_bag

        from ..sim.writer import run_pool
        from .plots import plot_by_distance, plot_sequence
        from .replay import ReplayConfig, _replay_star, replay_groups
        from .summary import answers_summary, format_answers, format_summary, summarize

        try:
            cfg = ReplayConfig(
                align=load_align_config(config),
                use_odometry=odometry,
                use_gnss=gnss,
                deskew=deskew,
                max_frames=max_frames,
                bev_images=bag_out is not None,
                unmeasured_every=unmeasured_every,
            )
        except ValueError as e:
            raise typer.BadParameter(str(e), param_hint="--config") from None
        if unmeasured_every is not None and through_service:
            _fail("--unmeasured-every: with --through-service the service decides which frames it measures")
        if bag_out is not None and bag_out.exists():
            _fail(f"--bag-out: {bag_out} exists already (a bag is written to a new folder)")
        bag = is_bag(root)
        if topic and not bag:
            _fail(f"--topic: {root} is not a ROS 2 bag (topics are for bags)")
        if bag:
            run = read_bag(root, _bag_topics(topic), max_frames=max_frames)
            typer.echo(
                f"{root}: {len(run)} frames (peer sweeps paired with an ego sweep; {run.skipped} without one)",
                err=True,
            )
            if through_service:  # a bag's stamps are a clock's: already positive wire stamps
                per_sequence = _through_service([(run.name, run.groups(), 0.0)], cfg)
            else:
                per_sequence = [replay_groups(run.name, run.groups(), cfg, progress=True)]
            frame_ids = [run.frame_ids]
        elif root.is_dir():
            scenarios = find_scenarios(root)[:limit]
            if not scenarios:
                _fail(f"{root}: no sequence folders under it")
            if through_service:
                sequences = [(name, islice(iter_scenario_frames(name, path), max_frames), 100.0)
                             for name, path in scenarios]  # fmt: skip
                per_sequence = _through_service(sequences, cfg)
            else:
                jobs = [(name, path, cfg) for name, path in scenarios]
                per_sequence = run_pool(_replay_star, jobs, workers, "replaying", "sequence")
            frame_ids = [{"ego": "ego", "peer": "peer"}] * len(per_sequence)
        else:
            _fail(f"{root}: neither a folder of sequences nor a ROS 2 bag (rosbag2 folder, .mcap or .db3)")
        if bag_out is not None:
            _write_bags(bag_out, per_sequence, frame_ids, cfg)
        records = [{k: v for k, v in r.items() if k != "bev_png"} for seq in per_sequence for r in seq]
        scored = all(r["t_err_m"] is not None for r in records)
        summary = summarize(records) if scored else answers_summary(records)
        summary["config"] = {
            "root": str(root),
            "odometry": odometry,
            "gnss": gnss,
            "track": cfg.align.track.model_dump(),
        }
        typer.echo(format_summary(summary) if scored else format_answers(summary))
        if json_out:
            json_out.parent.mkdir(parents=True, exist_ok=True)
            json_out.write_text(json.dumps(summary, indent=2))
        if records_out:
            records_out.parent.mkdir(parents=True, exist_ok=True)
            records_out.write_text("".join(json.dumps(r) + "\n" for r in records))
        if plots and scored:
            plots.mkdir(parents=True, exist_ok=True)
            plot_by_distance(summary, plots / "tracking_by_distance.png")
            for seq in per_sequence:
                if seq:
                    plot_sequence(seq, plots / f"track_{seq[0]['sequence'].replace('/', '_')}.png")


def _fail(problem: str) -> None:
    typer.secho(f"bb-align: {problem}", err=True, fg="red")
    raise typer.Exit(2)


def _bag_topics(pairs: list[str]):
    """``--topic KEY=TOPIC`` options -> BagTopics (an empty TOPIC: not used); one line and exit 2 when wrong."""
    from bb_align.io.rosbag import BagTopics

    given: dict = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep:
            _fail(f"--topic: {pair!r} is not KEY=TOPIC (e.g. peer_points=/car2/points)")
        given[key.strip()] = value.strip() or None
    try:
        return BagTopics(**given)
    except ValueError as e:
        errors = getattr(e, "errors", lambda: [])()
        if errors:
            key = ".".join(str(p) for p in errors[0]["loc"])
            if errors[0]["type"] == "extra_forbidden":
                known = ", ".join(BagTopics.model_fields)
                _fail(f"--topic: unknown key {key!r} (keys: {known})")
            _fail(f"--topic: {key}: {errors[0]['msg']}")
        _fail(f"--topic: {e}")


def _write_bags(out: Path, per_sequence: list[list[dict]], frame_ids: list[dict], cfg) -> None:
    from .bag_out import write_results_bag

    answer = cfg.align.answer
    for seq, ids in zip(per_sequence, frame_ids):
        if not seq:
            continue
        target = out if len(per_sequence) == 1 else out / seq[0]["sequence"].replace("/", "_")
        target.parent.mkdir(parents=True, exist_ok=True)
        path = write_results_bag(
            target,
            seq,
            ids,
            max_error_m=answer.max_error_m,
            max_error_deg=answer.max_error_deg,
            confidence=answer.confidence,
        )
        typer.echo(f"wrote {path}", err=True)


def _through_service(sequences: list, cfg) -> list[list[dict]]:
    """Each (name, frame groups, stamp offset) sent frame by frame to a `bb-align serve` child process started for
    the run (loopback, REST only, no authentication, stamps not checked against this clock, cfg.align), one peer
    id per sequence; the service is stopped after."""
    import tempfile

    import httpx
    from tqdm import tqdm

    from bb_align.server.settings import Settings

    from ..harness import free_port, start_service
    from .through_service import replay_groups_through_service

    settings = Settings(
        profile="demo",  # loopback only, no credentials: the service lives for this run
        host="127.0.0.1",
        port=free_port(),
        zenoh={"enabled": False},
        align=cfg.align,
        limits={"check_stamp_clock": False, "rest_rate_hz": 1000.0, "rest_burst": 1000.0},
    )
    out = []
    with tempfile.TemporaryDirectory(prefix="bbalign-track-") as tmp:
        svc = start_service(settings, None, Path(tmp))
        try:
            with httpx.Client(base_url=svc.rest, timeout=300) as http:
                for i, (name, groups, offset) in enumerate(sequences):
                    out.append(
                        replay_groups_through_service(
                            http, name, tqdm(groups, desc=name, unit="frame", leave=False), f"seq{i}",
                            odometry=cfg.use_odometry, gnss=cfg.use_gnss, stamp_offset_s=offset,
                            bev=cfg.align.bev.model_dump(), bev_images=cfg.bev_images, deskew=cfg.deskew,
                        )
                    )  # fmt: skip
        finally:
            svc.stop()
    return out
