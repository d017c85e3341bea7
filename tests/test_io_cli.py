import json

import numpy as np
import pytest
from typer.testing import CliRunner

from bb_align.cli import app
from bb_align.engine.geometry import pose_error
from bb_align.io.clouds import load_boxes, load_cloud, save_boxes_json
from test_pipeline import _pair, world  # noqa: F401  (fixture)


def test_cloud_formats_round_trip(tmp_path):
    pts = np.random.default_rng(0).uniform(-10, 10, (100, 4)).astype(np.float32)
    pts.tofile(tmp_path / "a.bin")
    np.save(tmp_path / "a.npy", pts[:, :3])
    from pypcd4 import PointCloud

    PointCloud.from_xyzi_points(pts).save(tmp_path / "a.pcd")
    np.testing.assert_array_equal(load_cloud(tmp_path / "a.bin"), pts)
    np.testing.assert_array_equal(load_cloud(tmp_path / "a.npy"), pts[:, :3])
    np.testing.assert_allclose(load_cloud(tmp_path / "a.pcd"), pts)
    five = np.zeros((7, 5), np.float32)
    five.tofile(tmp_path / "b.bin")
    assert load_cloud(tmp_path / "b.bin").shape == (7, 5)
    with pytest.raises(ValueError, match="unknown cloud format"):
        load_cloud(tmp_path / "a.txt")


def test_boxes_json_and_csv(tmp_path):
    boxes = np.array([[1, 2, 0.5, 4.2, 1.8, 1.5, 0.3], [-5, 7, 0.7, 4.0, 1.9, 1.6, -2.0]])
    save_boxes_json(tmp_path / "b.json", boxes)
    np.testing.assert_allclose(load_boxes(tmp_path / "b.json"), boxes)
    rows = "yaw,x,y,z,l,w,h\n" + "\n".join(",".join(map(str, [b[6], *b[:6]])) for b in boxes)
    (tmp_path / "b.csv").write_text(rows)
    np.testing.assert_allclose(load_boxes(tmp_path / "b.csv"), boxes)
    (tmp_path / "bad.csv").write_text("x,y\n1,2\n")
    with pytest.raises(ValueError, match="lacks columns"):
        load_boxes(tmp_path / "bad.csv")


def test_cli_align_json_and_plot(tmp_path, world):  # noqa: F811
    pts_ego, boxes_ego, pts_peer, boxes_peer, T_true = _pair(world, -120.0, (20.0, 5.0))
    np.save(tmp_path / "ego.npy", pts_ego)
    np.column_stack([pts_peer, np.zeros(len(pts_peer), np.float32)]).tofile(tmp_path / "peer.bin")
    save_boxes_json(tmp_path / "ego_boxes.json", boxes_ego)
    save_boxes_json(tmp_path / "peer_boxes.json", boxes_peer)
    runner = CliRunner()
    out = runner.invoke(
        app,
        [
            "align",
            str(tmp_path / "ego.npy"),
            str(tmp_path / "peer.bin"),
            "--ego-boxes",
            str(tmp_path / "ego_boxes.json"),
            "--peer-boxes",
            str(tmp_path / "peer_boxes.json"),
            "--json",
            "--plot",
            str(tmp_path / "fig.png"),
        ],
    )
    assert out.exit_code == 0, out.output
    res = json.loads(out.stdout)
    for key in ("T_ego_peer", "yaw_deg", "tx", "ty", "inliers_bv", "inliers_box", "success", "confidence"):
        assert key in res
    assert res["success"] and res["inliers_box"] > 6
    t_err, r_err = pose_error(np.array(res["T_ego_peer"]), T_true)
    assert t_err < 0.3 and r_err < 0.3
    assert (tmp_path / "fig.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    out = runner.invoke(app, ["align", str(tmp_path / "ego.npy"), str(tmp_path / "peer.bin")])
    assert out.exit_code == 0 and "stage 2 skipped" in out.stdout


def test_cli_align_exits_3_on_a_failed_alignment_and_config_files_drive_it(tmp_path, world):  # noqa: F811
    """A failed alignment is a non-zero exit (3), with --json too; --config loads a saved AlignConfig (JSON or
    YAML, missing fields default) and it changes the run: an impossible uncertainty bound turns success into failure."""
    import yaml

    from bb_align.cli import ALIGN_FAILED
    from bb_align.engine.config import AlignConfig

    pts_ego, _, pts_peer, _, _ = _pair(world, 30.0, (10.0, -4.0))
    np.save(tmp_path / "ego.npy", pts_ego)
    np.save(tmp_path / "peer.npy", pts_peer)
    runner = CliRunner()
    args = ["align", str(tmp_path / "ego.npy"), str(tmp_path / "peer.npy"), "--json"]
    ok = runner.invoke(app, args)
    assert ok.exit_code == 0 and json.loads(ok.stdout)["success"], ok.output

    dumped = runner.invoke(app, ["config", "--dump"])
    assert dumped.exit_code == 0
    assert AlignConfig.model_validate_json(dumped.stdout) == AlignConfig()  # the dump is the defaults, loadable
    strict = json.loads(dumped.stdout)
    strict["covariance"]["max_sigma_m"] = 1e-6
    (tmp_path / "strict.json").write_text(json.dumps(strict))
    (tmp_path / "strict.yaml").write_text(yaml.safe_dump({"covariance": {"max_sigma_m": 1e-6}}))
    for cfg_file in ("strict.json", "strict.yaml"):
        failed = runner.invoke(app, [*args, "--config", str(tmp_path / cfg_file)])
        assert failed.exit_code == ALIGN_FAILED == 3, failed.output
        assert json.loads(failed.stdout)["reason"] == "degenerate_pose"
    plain = runner.invoke(app, args[:3] + ["--config", str(tmp_path / "strict.yaml")])
    assert plain.exit_code == 3 and "FAILED (degenerate_pose)" in plain.stdout

    (tmp_path / "bad.yaml").write_text(yaml.safe_dump({"success": {"min_inliers_bv": -1}}))
    bad = runner.invoke(app, [*args, "--config", str(tmp_path / "bad.yaml")])
    assert bad.exit_code == 2 and "min_inliers_bv" in bad.output


def test_plot_labels_each_image_and_draws_a_metre_scale():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bb_align.engine.bev import BevImage
    from bb_align.io.plot import _label_and_scale, scale_bar_m

    assert scale_bar_m(100.0) == 20.0 and scale_bar_m(160.0) == 20.0 and scale_bar_m(30.0) == 5.0
    assert scale_bar_m(2.0) == 1.0
    bev = BevImage(np.zeros((500, 500), np.uint8), resolution_m=0.2, range_m=50.0)  # 100 m wide
    fig, ax = plt.subplots()
    assert _label_and_scale(ax, bev, "peer", col0=500) == (20.0, 100.0)  # 20 m = 100 px at 0.2 m/px
    texts = [t.get_text() for t in ax.texts]
    assert texts == ["peer", "20 m"]
    (bar,) = ax.lines
    np.testing.assert_allclose(bar.get_xdata(), [520.0, 620.0])  # inside the second image, 100 px long
    plt.close(fig)


@pytest.mark.parametrize(
    "text, message",
    [
        ("1 0 0\n0 1 0\n", "expected a finite 4x4 or 3x3 matrix"),
        ("2 0 0 1\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "not a rigid transform"),
        ("a b c\n", "not a plain-text matrix"),
    ],
)
def test_align_refuses_a_bad_prior_file_in_one_line(tmp_path, text, message):
    pts = np.random.default_rng(0).uniform(-10, 10, (2000, 4)).astype(np.float32)
    pts.tofile(tmp_path / "a.bin")
    (tmp_path / "prior.txt").write_text(text)
    out = CliRunner().invoke(
        app, ["align", str(tmp_path / "a.bin"), str(tmp_path / "a.bin"), "--prior", str(tmp_path / "prior.txt")]
    )
    assert out.exit_code == 2
    flat = " ".join(out.output.replace("│", " ").split())  # the error box wraps long lines
    assert message in flat and "Traceback" not in out.output
