"""The `bb-align` command line. Each feature area registers its own commands (register(app))."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

app = typer.Typer(no_args_is_help=True, add_completion=False,
                  help="BB-Align: V2V relative pose recovery from LiDAR BV images and object boxes.")


@app.callback()
def main() -> None:
    """BB-Align: V2V relative pose recovery from LiDAR BV images and object boxes."""


@app.command()
def align(
    ego_cloud: Path = typer.Argument(..., exists=True, dir_okay=False,
                                     help="ego cloud: .bin (4/5 float32 cols), .npy, .pcd"),
    peer_cloud: Path = typer.Argument(..., exists=True, dir_okay=False, help="peer cloud, same formats"),
    ego_boxes: Optional[Path] = typer.Option(None, exists=True, dir_okay=False,
                                             help="ego boxes: JSON or CSV x,y,z,l,w,h,yaw"),
    peer_boxes: Optional[Path] = typer.Option(None, exists=True, dir_okay=False, help="peer boxes: JSON or CSV"),
    json_out: bool = typer.Option(False, "--json", help="print one JSON object on stdout"),
    plot: Optional[Path] = typer.Option(None, help="write a diagnostic PNG (matches and aligned overlay)"),
    range_m: Optional[float] = typer.Option(None, help="BV half width R in metres (default from config)"),
    resolution_m: Optional[float] = typer.Option(None, help="BV cell size in metres (default from config)"),
) -> None:
    """Recover T_ego_peer from two LiDAR clouds (and optionally their detected boxes)."""
    from bb_align.engine.config import AlignConfig
    from bb_align.engine.pipeline import Aligner
    from bb_align.io.clouds import load_boxes, load_cloud

    cfg = AlignConfig()
    bev_over = {k: v for k, v in (("range_m", range_m), ("resolution_m", resolution_m)) if v is not None}
    if bev_over:
        cfg = cfg.model_copy(update={"bev": cfg.bev.model_copy(update=bev_over)})
    aligner = Aligner(cfg)
    ego = aligner.prepare(load_cloud(ego_cloud), load_boxes(ego_boxes) if ego_boxes else None, keep_maps=True)
    peer = aligner.prepare(load_cloud(peer_cloud), load_boxes(peer_boxes) if peer_boxes else None, keep_maps=True)
    result = aligner.align(ego, peer)
    if plot is not None:
        from bb_align.io.plot import plot_alignment

        plot_alignment(plot, ego.bev, peer.bev, result, ego.boxes, peer.boxes,
                       title=f"{ego_cloud.name} <- {peer_cloud.name}")
    if json_out:
        typer.echo(json.dumps(result.to_dict()))
        return
    status = "success" if result.success else f"FAILED ({result.reason})"
    typer.echo(f"{status}: yaw {result.yaw_deg:.3f} deg, tx {result.tx:.3f} m, ty {result.ty:.3f} m, "
               f"inliers_bv {result.inliers_bv}/{result.matches_bv}, inliers_box {result.inliers_box}, "
               f"confidence {result.confidence:.2f}")
    for note in result.notes:
        typer.echo(f"note: {note}")
    typer.echo("T_ego_peer =\n" + "\n".join("  " + " ".join(f"{v: .6f}" for v in row) for row in result.T_ego_peer))
    typer.echo("timings (ms): " + ", ".join(f"{k} {v:.1f}" for k, v in
                                            {**ego.timings_ms, **result.timings_ms}.items()))
    if plot is not None:
        typer.echo(f"plot: {plot}")


# Feature areas register their commands below (one line each).
from bb_align.server.commands import register as _register_service; _register_service(app)  # serve, demo, wire-schemas
from bb_align.lab.evaluation.cli import register as _register_evaluation; _register_evaluation(app)  # sim, eval
from bb_align.lab.bench.cli import register as _register_bench; _register_bench(app)  # bench
