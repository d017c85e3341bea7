"""``bb-align recover``: a corrected copy of an OPV2V / V2V4Real dataset (registered into the CLI)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import typer

from .defaults import DESKEW_DEFAULT, DESKEW_HELP


def parse_pose_noise(text: str) -> tuple[float, float]:
    try:
        parts = [float(v) for v in text.split(",")]
    except ValueError:
        parts = []
    if len(parts) != 2 or min(parts) < 0:
        raise typer.BadParameter("--pose-noise takes 'SIGMA_T_M,SIGMA_THETA_DEG', two numbers >= 0, e.g. 2,2")
    return parts[0], parts[1]


def register(app: typer.Typer, simulated_detections: Callable[[int], object] | None = None) -> None:
    """Add ``recover``. ``simulated_detections(seed)`` makes the detection source of --simulate-detections
    (it lives in the lab; the CLI passes it in)."""

    @app.command("recover")
    def recover_cmd(
        root: Path = typer.Argument(
            ...,
            exists=True,
            file_okay=False,
            help="dataset root: ROOT/<scenario>/... or ROOT/<split>/<scenario>/..., or a DAIR-V2X-C root",
        ),
        out: Path = typer.Argument(..., file_okay=False, help="where to write the corrected copy (not inside ROOT)"),
        prior: bool = typer.Option(False, "--prior", help="gate the engine's matches by the reported (noisy) pose"),
        track: bool = typer.Option(
            False, "--track", help="follow each peer through its scenario's frames (acquire once, then refine)"
        ),
        detections: Path | None = typer.Option(
            None,
            "--detections",
            exists=True,
            file_okay=False,
            help="per-frame detection files DIR/<scenario>/<agent>/<timestamp>.npy|.json|.txt (README: format)",
        ),
        simulate_detections: bool = typer.Option(
            False, "--simulate-detections", help="simulate detections from the ground-truth labels (a stand-in)"
        ),
        pose_noise: str | None = typer.Option(
            None,
            "--pose-noise",
            help="demo: add Gaussian noise 'SIGMA_T_M,SIGMA_THETA_DEG' to each non-ego pose before recovering",
        ),
        seed: int = typer.Option(0, "--seed", help="seed of --pose-noise and --simulate-detections"),
        copy: bool = typer.Option(False, "--copy", help="copy point clouds instead of hard-linking them"),
        limit: int | None = typer.Option(None, "--limit", min=1, help="stop after this many frames (resumable)"),
        config: Path | None = typer.Option(
            None, exists=True, dir_okay=False, help="an AlignConfig as JSON or YAML (`bb-align config --dump`)"
        ),
        quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
        deskew: bool = typer.Option(DESKEW_DEFAULT, "--deskew/--no-deskew", help=DESKEW_HELP),
    ) -> None:
        """Recover each non-ego agent's pose relative to the ego, frame by frame, and write a copy of the
        dataset to OUT with the recovered lidar_pose (failures keep the reported one) plus
        OUT/recovered_poses.jsonl. Rerun the same command to resume an interrupted run.

        On a DAIR-V2X-C root (cooperative-vehicle-infrastructure or its parent) the vehicle is the ego, the
        roadside unit the peer, the boxes are the labels, and OUT's cooperative/calib/lidar_i2v/<id>.json holds
        the recovered transform (x, y, yaw recovered; z, roll, pitch kept)."""
        _recover(
            root, out, prior, track, detections, simulate_detections, pose_noise, seed, copy, limit, config, quiet,
            simulated_detections, deskew,
        )  # fmt: skip


def _recover(
    root,
    out,
    prior,
    track,
    detections,
    simulate_detections,
    pose_noise,
    seed,
    copy,
    limit,
    config,
    quiet,
    simulated,
    deskew,
) -> None:
    """The ``recover`` command's work (its options as named there; ``simulated``: register's factory)."""
    from .config_file import load_align_config
    from .dataset import is_dair_root
    from .recover import RecoverConfig, YamlDetections, recover_dataset

    source = _detection_source(detections, simulate_detections, seed, simulated)
    sigma_t, sigma_deg = parse_pose_noise(pose_noise) if pose_noise is not None else (0.0, 0.0)
    try:
        align_cfg = load_align_config(config)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--config") from None
    cfg = RecoverConfig(
        align=align_cfg,
        use_prior=prior,
        track=track,
        pose_noise_t_m=sigma_t,
        pose_noise_deg=sigma_deg,
        seed=seed,
        link=not copy,
        deskew=deskew,
    )
    dair = is_dair_root(root)
    typer.echo(f"detections: {'labels' if dair and isinstance(source, YamlDetections) else source.name}")
    try:
        summary = recover_dataset(root, out, cfg, source, limit=limit, progress=not quiet)
    except (ValueError, FileNotFoundError) as exc:
        raise typer.BadParameter(str(exc)) from exc
    _echo_summary(summary, out)


def _detection_source(detections: Path | None, simulate: bool, seed: int, simulated):
    """Where the boxes come from: a folder of detection files, the simulated detector, or the yaml's."""
    from .recover import FolderDetections, YamlDetections

    if detections is not None and simulate:
        raise typer.BadParameter("give --detections DIR or --simulate-detections, not both")
    if simulate:
        if simulated is None:
            raise typer.BadParameter("--simulate-detections is not available in this build")
        return simulated(seed)
    return FolderDetections(detections) if detections is not None else YamlDetections()


def _echo_summary(summary: dict, out: Path) -> None:
    from .recover import JSONL_NAME, SUMMARY_NAME

    typer.echo(
        f"frames {summary['frames_done']}/{summary['frames']}, agent frames {summary['agent_frames']}: "
        f"recovered {summary['recovered']}, kept the reported pose {summary['kept_reported']}"
    )
    typer.echo("outcomes: " + json.dumps(summary["outcomes"]))
    if summary.get("frames_left_out"):
        left = summary["frames_left_out"]
        typer.echo(f"note: {len(left)} cooperative frames left out (files missing), e.g. {left[0]}")
    boxes = summary["agent_frames_with_boxes"]
    if boxes["ego"] < summary["agent_frames"] or boxes["peer"] < summary["agent_frames"]:
        typer.echo(
            f"note: boxes for {boxes['ego']} ego and {boxes['peer']} peer of {summary['agent_frames']} agent "
            "frames; without boxes stage 2 is skipped (--detections DIR, or --simulate-detections)"
        )
    typer.echo(f"poses: {Path(out) / JSONL_NAME}")
    if summary["complete"]:
        typer.echo(f"summary: {Path(out) / SUMMARY_NAME}")
    else:
        typer.echo("stopped before the end (--limit): run the same command again to continue")
