"""The `bb-align` command line. Each feature area registers its own commands (register(app)).

Exit codes: 0 done; 1 a run failed (e.g. the demo got no result); 2 bad usage or input; 3 ``bb-align align`` ran
but the alignment failed (the reason is printed; with --json it is in the object).
"""

from __future__ import annotations

import json
import os
import sys
from importlib import import_module
from pathlib import Path
from typing import NoReturn

import click
import typer
from typer.core import TyperGroup

from bb_align.io.errors import InputFileError, MissingExtraError

# Commands whose modules are costly to import, loaded only when run (their help line is given here), so that
# `bb-align --help` stays fast: name -> (module, function, one-line help).
LAZY_COMMANDS = {
    "soak": (
        "bb_align.lab.soak",
        "soak",
        "Drive a service with valid and hostile traffic over Zenoh on loopback and account for every message.",
    ),
}


class _LazyCommand(click.Command):
    """Stands in for a command in the listing; the real one is built on first use."""

    def __init__(self, name: str, module: str, function: str, short_help: str):
        super().__init__(name, short_help=short_help, help=short_help)
        self._target = (module, function)
        self._real: click.Command | None = None

    def real(self) -> click.Command:
        if self._real is None:
            module, function = self._target
            single = typer.Typer(add_completion=False, rich_markup_mode=None)
            single.command(self.name)(getattr(import_module(module), function))
            self._real = typer.main.get_command(single)
        return self._real

    def make_context(self, info_name, args, parent=None, **extra):
        return self.real().make_context(info_name, args, parent=parent, **extra)

    def invoke(self, ctx):
        return self.real().invoke(ctx)


class _Group(TyperGroup):
    """The root command: lazy commands; a bad input file or a missing extra is one line and exit code 2."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        for name, (module, function, short_help) in LAZY_COMMANDS.items():
            self.add_command(_LazyCommand(name, module, function, short_help))

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (InputFileError, MissingExtraError) as e:
            _refuse(str(e))
        except typer.BadParameter as e:  # typer's click (it vendors one in recent versions)
            if any(c.__name__ == "MissingParameter" for c in type(e).__mro__):
                raise  # a missing argument or option: usage, as for a wrong command or option name
            _refuse(f"{_hint(e) or ctx.invoked_subcommand}: {e.message}")  # a bad value: one line, no usage
        except BrokenPipeError:  # the reader went away (`| head -1`): stop quietly
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            raise typer.Exit(0) from None


def _refuse(message: str) -> NoReturn:
    """``bb-align: WHAT: problem`` on stderr, one line, exit code 2."""
    typer.secho(f"bb-align: {' '.join(message.split())}", err=True, fg="red")
    raise typer.Exit(2) from None


def _hint(e: typer.BadParameter) -> str | None:
    """What the bad value was given for: '--prior', 'ego_cloud' (click's hint without its quotes)."""
    if e.param_hint is not None:
        hints = [e.param_hint] if isinstance(e.param_hint, str) else list(e.param_hint)
        return " / ".join(hints)
    if e.param is not None:
        return " / ".join(e.param.opts) or e.param.name
    return None


# Plain help and errors (rich_markup_mode=None): flags read as flags (`--json`, not `--json <bool>`) and a usage
# error is one line.
app = typer.Typer(
    cls=_Group,
    rich_markup_mode=None,
    no_args_is_help=True,
    add_completion=False,
    help="BB-Align: V2V relative pose recovery from LiDAR BV images and object boxes.",
)


@app.callback()
def main() -> None:
    """BB-Align: V2V relative pose recovery from LiDAR BV images and object boxes."""


@app.command()
def align(
    ego_cloud: Path = typer.Argument(
        ...,
        exists=True,
        help="ego cloud: .bin (4/5 float32 cols), .npy, .pcd; or a folder of the ego's frames with odometry (the "
        "sequence layout of `bb-align track`): the last --frames of both folders are aligned together",
    ),
    peer_cloud: Path = typer.Argument(..., exists=True, help="peer cloud, same formats; or the peer's folder"),
    ego_boxes: Path | None = typer.Option(
        None, exists=True, dir_okay=False, help="ego boxes: JSON or CSV x,y,z,l,w,h,yaw"
    ),
    peer_boxes: Path | None = typer.Option(None, exists=True, dir_okay=False, help="peer boxes: JSON or CSV"),
    json_out: bool = typer.Option(False, "--json", help="print one JSON object on stdout"),
    plot: Path | None = typer.Option(None, help="write a diagnostic PNG (matches and aligned overlay)"),
    range_m: float | None = typer.Option(None, help="BV half width R in metres (default from config)"),
    resolution_m: float | None = typer.Option(None, help="BV cell size in metres (default from config)"),
    config: Path | None = typer.Option(
        None,
        exists=True,
        dir_okay=False,
        help="an AlignConfig saved as JSON or YAML (see `bb-align config --dump`); "
        "fields it leaves out keep their defaults",
    ),
    prior: Path | None = typer.Option(
        None,
        exists=True,
        dir_okay=False,
        help="a prior T_ego_peer: a 4x4 (or 3x3 ground-plane) matrix as plain text, e.g. composed from both cars' "
        "reported poses (two folders: at their last frame pair); the answer must lie within config "
        "prior.max_translation_m / max_yaw_deg of it",
    ),
    frames: int | None = typer.Option(
        None, min=1, max=50, help="two folders: align their last this many frame pairs (default config stream.frames)"
    ),
) -> None:
    """Recover T_ego_peer from two LiDAR clouds (and optionally their detected boxes), or at the last of two cars'
    recent frames from their folders (a second of stream, each car's odometry: Aligner.align_stream). Exits 3 when
    the alignment fails (success=false; the reason is printed)."""
    from bb_align.engine.pipeline import Aligner
    from bb_align.io.clouds import load_boxes

    if ego_cloud.is_dir() != peer_cloud.is_dir():
        raise typer.BadParameter("give two clouds or two folders of frames", param_hint="PEER_CLOUD")
    stream = ego_cloud.is_dir()
    if stream and (ego_boxes or peer_boxes or plot):
        raise typer.BadParameter("two folders take their boxes from their yaml files; no plot", param_hint="--plot")

    if plot is not None:  # fail now, not after the alignment
        from bb_align.io.plot import pyplot

        pyplot()
    cfg = _load_config(config)
    bev_over = {k: v for k, v in (("range_m", range_m), ("resolution_m", resolution_m)) if v is not None}
    if bev_over:
        cfg = cfg.model_copy(update={"bev": cfg.bev.model_copy(update=bev_over)})
    aligner = Aligner(cfg)
    T_prior = _load_prior(prior) if prior is not None else None
    if stream:
        return _align_stream(aligner, ego_cloud, peer_cloud, frames or cfg.stream.frames, json_out, T_prior)
    pts_ego, pts_peer = _points(ego_cloud), _points(peer_cloud)
    ego = aligner.prepare(pts_ego, load_boxes(ego_boxes) if ego_boxes else None, keep_maps=True)
    peer = aligner.prepare(pts_peer, load_boxes(peer_boxes) if peer_boxes else None, keep_maps=True)
    result = aligner.align(ego, peer, T_prior=T_prior)
    if plot is not None:
        from bb_align.io.plot import plot_alignment

        plot_alignment(
            plot, ego.bev, peer.bev, result, ego.boxes, peer.boxes, title=f"{ego_cloud.name} <- {peer_cloud.name}"
        )
    if json_out:
        typer.echo(json.dumps({**result.to_dict(), "prior_used": T_prior is not None}))
        raise typer.Exit(0 if result.success else ALIGN_FAILED)
    _print_result(result, ego.timings_ms)
    if T_prior is not None:
        typer.echo(f"prior: {prior} (used)")
    if plot is not None:
        typer.echo(f"plot: {plot}")
    if not result.success:
        raise typer.Exit(ALIGN_FAILED)


def _align_stream(aligner, ego_dir: Path, peer_dir: Path, frames: int, json_out: bool, T_prior=None) -> None:
    """`align` over two folders: the last ``frames`` pairs together (bb_align.io.streams), ``T_prior`` at the last."""
    import numpy as np

    from bb_align.engine.geometry import pose_error
    from bb_align.io.streams import stream_frames

    try:
        pairs, ego, peer = stream_frames(aligner, ego_dir, peer_dir, frames)
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint="EGO_CLOUD / PEER_CLOUD") from None
    result = aligner.align_stream(pairs, T_prior)
    truth = None
    if ego.T_world_sensor is not None and peer.T_world_sensor is not None:
        truth = pose_error(result.T_ego_peer, np.linalg.inv(ego.T_world_sensor) @ peer.T_world_sensor)
    if json_out:
        body = {**result.to_dict(), "frames": len(pairs), "frame": peer.timestamp, "prior_used": T_prior is not None}
        if truth is not None:
            body["error_vs_lidar_pose"] = {"t_m": truth[0], "r_deg": truth[1]}
        typer.echo(json.dumps(body))
        raise typer.Exit(0 if result.success else ALIGN_FAILED)
    typer.echo(f"{len(pairs)} frame pairs of {ego_dir} and {peer_dir}, the last {peer.timestamp}")
    _print_result(result, {})
    if truth is not None:
        typer.echo(f"against the yaml's lidar_pose: {truth[0]:.2f} m / {truth[1]:.2f} deg")
    if not result.success:
        raise typer.Exit(ALIGN_FAILED)


def _print_result(result, prepare_ms: dict) -> None:
    status = "success" if result.success else f"FAILED ({result.reason})"
    typer.echo(
        f"{status}: yaw {result.yaw_deg:.3f} deg, tx {result.tx:.3f} m, ty {result.ty:.3f} m, "
        f"inliers_bv {result.inliers_bv}/{result.matches_bv}, inliers_box {result.inliers_box}, "
        f"confidence {result.confidence:.2f}"
    )
    if result.covariance is not None:
        import numpy as np

        sig = np.sqrt(np.clip(np.linalg.eigvalsh(np.asarray(result.covariance)[1:, 1:]), 0, None))
        yaw_sig = np.degrees(np.sqrt(max(float(result.covariance[0][0]), 0.0)))
        typer.echo(
            f"1-sigma: translation {sig[0]:.2f} m / {sig[1]:.2f} m (best / worst direction), yaw {yaw_sig:.2f} deg"
        )
    for note in result.notes:
        typer.echo(f"note: {note}")
    typer.echo("T_ego_peer =\n" + "\n".join("  " + " ".join(f"{v: .6f}" for v in row) for row in result.T_ego_peer))
    typer.echo("timings (ms): " + ", ".join(f"{k} {v:.1f}" for k, v in {**prepare_ms, **result.timings_ms}.items()))


ALIGN_FAILED = 3  # exit code of `bb-align align` when the alignment failed


def _points(path: Path):
    """A cloud with at least one point: an empty file or one without a finite x, y, z is bad input (exit 2), not a
    failed alignment (exit 3)."""
    from bb_align.io.clouds import load_cloud

    pts = load_cloud(path)
    if len(pts) == 0:
        raise InputFileError(f"{path}: no point with a finite x, y, z (an empty cloud)")
    return pts


def _load_prior(path: Path):
    """A prior T_ego_peer from a plain-text 4x4 (or 3x3 ground-plane) matrix, checked to be a rigid transform."""
    import numpy as np

    shapes = "a 4x4 rigid transform [R t; 0 0 0 1] or a 3x3 ground-plane one [cos -sin tx; sin cos ty; 0 0 1]"
    try:
        T = np.loadtxt(path, ndmin=2)
    except ValueError as e:
        raise typer.BadParameter(
            f"{path}: not a plain-text matrix ({e}); expected {shapes}", param_hint="--prior"
        ) from None
    if T.shape not in {(4, 4), (3, 3)}:
        raise typer.BadParameter(
            f"{path}: got a {'x'.join(map(str, T.shape))} matrix; expected {shapes}", param_hint="--prior"
        )
    if not np.all(np.isfinite(T)):
        raise typer.BadParameter(f"{path}: the matrix holds NaN or inf; expected {shapes}", param_hint="--prior")
    n = T.shape[0] - 1
    R = T[:n, :n]
    if not np.allclose(T[n], np.eye(n + 1)[n], atol=1e-6):
        raise typer.BadParameter(
            f"{path}: the last row is {T[n].tolist()}, not {np.eye(n + 1)[n].tolist()}: expected {shapes}"
            + (" (a 3x3 rotation alone is not a prior: give the 4x4 with its translation)" if n == 2 else ""),
            param_hint="--prior",
        )
    if not np.allclose(R @ R.T, np.eye(n), atol=1e-3) or np.linalg.det(R) < 0:
        raise typer.BadParameter(
            f"{path}: the top-left {n}x{n} block is not a rotation (R R^T = I, det +1): expected {shapes}",
            param_hint="--prior",
        )
    return T


def _load_config(path: Path | None, option: str = "--config"):
    """An AlignConfig from a JSON or YAML file (defaults for what it leaves out); the defaults without one.
    A bad file is blamed on ``option``, the option that named it."""
    from bb_align.io.config_file import load_align_config

    try:
        return load_align_config(path)
    except ValueError as e:
        raise typer.BadParameter(str(e), param_hint=option) from None


@app.command("config")
def config_cmd(
    dump: bool = typer.Option(
        False, "--dump", help="print the engine's default AlignConfig as JSON (the user's knobs)"
    ),
    advanced: bool = typer.Option(False, "--advanced", help="with --dump or --check: every setting"),
    check: Path | None = typer.Option(
        None, exists=True, dir_okay=False, help="validate a saved config file and print it with defaults filled in"
    ),
) -> None:
    """The engine's configuration and its defaults (service: BBALIGN_ALIGN__<SECTION>__<NAME>). --dump shows the
    settings a user tunes; --advanced adds the calibrated ones (docs/configuration.md)."""
    if not dump and check is None:
        raise typer.BadParameter("give --dump or --check FILE")
    typer.echo(json.dumps(_load_config(check, option="--check").dump(advanced=advanced), indent=2))


def _register_feature_commands() -> None:
    """Each feature area adds its own commands."""
    from bb_align.io.commands import register as io  # recover
    from bb_align.lab.bench.cli import register as bench  # bench
    from bb_align.lab.commands import register as lab  # demo, soak
    from bb_align.lab.evaluation.cli import register as evaluation  # sim, eval
    from bb_align.lab.realpairs_cli import register as real_pairs  # real-pairs
    from bb_align.lab.tracking.cli import register as tracking  # track
    from bb_align.server.commands import register as server  # serve, wire-schemas

    for register in (server, lab, evaluation, tracking, bench, real_pairs):
        register(app)
    io(app, simulated_detections=_simulated_detections)


def _simulated_detections(seed: int):
    """The detection source of `recover --simulate-detections` (the detector model lives in the lab)."""
    from bb_align.lab.sim.detections import GroundTruthDetections

    return GroundTruthDetections(seed=seed)


_register_feature_commands()
