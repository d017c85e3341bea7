import json
import subprocess
import sys

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
    strict["answer"]["max_error_m"] = 1e-6
    (tmp_path / "strict.json").write_text(json.dumps(strict))
    (tmp_path / "strict.yaml").write_text(yaml.safe_dump({"answer": {"max_error_m": 1e-6}}))
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
        ("1 0 0\n0 1 0\n", "got a 2x3 matrix; expected a 4x4 rigid transform"),
        ("2 0 0 1\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "is not a rotation"),
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


def _bad_input_files(tmp_path):
    """(file, what the one-line error must name) for clouds and boxes a user may really hand the CLI."""
    np.save(tmp_path / "two_columns.npy", np.zeros((10, 2), np.float32))
    np.zeros(11, np.float32).tofile(tmp_path / "eleven.bin")
    (tmp_path / "scan.ply").write_text("ply\nformat ascii 1.0\n")
    (tmp_path / "text.npy").write_text("1 2 3\n")
    (tmp_path / "empty.bin").write_bytes(b"")
    (tmp_path / "no_z.json").write_text(json.dumps([{"x": 1, "y": 2, "l": 4, "w": 2, "h": 1.5, "yaw": 0}]))
    (tmp_path / "short.json").write_text(json.dumps([[1, 2, 3, 4, 5, 6]]))
    (tmp_path / "word.json").write_text(json.dumps([{"x": 1, "y": 2, "z": 0, "l": "long", "w": 2, "h": 1, "yaw": 0}]))
    (tmp_path / "nan.csv").write_text("x,y,z,l,w,h,yaw\n1,2,0,nan,2,1,0\n")
    (tmp_path / "no_yaw.csv").write_text("x,y,z,l,w,h\n1,2,0,4,2,1\n")
    clouds = {
        "two_columns.npy": "shape (10, 2)",
        "eleven.bin": "11 float32 values",
        "scan.ply": "'.ply'",
        "text.npy": "not a .npy file",
        "empty.bin": "empty file",
    }
    boxes = {
        "no_z.json": "box 0 lacks z",
        "short.json": "box 0 has 6 numbers (needs 7",
        "word.json": "box 0 l is 'long', not a number",
        "nan.csv": "boxes[0] l is nan",
        "no_yaw.csv": "lacks columns ['yaw']",
    }
    return clouds, boxes


def test_bad_cloud_and_box_files_raise_input_file_error_naming_file_and_field(tmp_path):
    from bb_align.io.clouds import InputFileError

    clouds, boxes = _bad_input_files(tmp_path)
    for name, says in clouds.items():
        with pytest.raises(InputFileError) as e:
            load_cloud(tmp_path / name)
        assert name in str(e.value) and says in str(e.value), str(e.value)
    for name, says in boxes.items():
        with pytest.raises(InputFileError) as e:
            load_boxes(tmp_path / name)
        assert name in str(e.value) and says in str(e.value), str(e.value)


def test_a_cloud_drops_rows_without_a_return(tmp_path):
    pts = np.array([[1, 2, 3, 0.5], [np.nan, np.nan, np.nan, 0], [4, 5, 6, 0.1]], np.float32)
    np.save(tmp_path / "organised.npy", pts)
    np.testing.assert_array_equal(load_cloud(tmp_path / "organised.npy"), pts[[0, 2]])


def test_cli_bad_input_file_exits_2_with_one_line_and_no_traceback(tmp_path):
    clouds, boxes = _bad_input_files(tmp_path)
    good = tmp_path / "good.npy"
    np.save(good, np.random.default_rng(0).uniform(-20, 20, (500, 3)).astype(np.float32))
    runner = CliRunner()
    cases = [["align", str(tmp_path / n), str(good)] for n in clouds]
    cases += [["align", str(good), str(good), "--ego-boxes", str(tmp_path / n)] for n in boxes]
    for args, says in zip(cases, [*clouds.values(), *boxes.values()]):
        out = runner.invoke(app, args)
        assert out.exit_code == 2, (args, out.output)
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("bb-align: ") and says in lines[0], out.stderr
        assert "Traceback" not in out.output and out.stdout == ""


def test_config_dump_shows_the_users_knobs_and_advanced_shows_every_setting():
    from bb_align.engine.config import USER_FACING, AlignConfig

    runner = CliRunner()
    small = json.loads(runner.invoke(app, ["config", "--dump"]).stdout)
    full = json.loads(runner.invoke(app, ["config", "--dump", "--advanced"]).stdout)

    def leaves(d, prefix=""):
        return [
            k for key, v in d.items() for k in (leaves(v, f"{prefix}{key}.") if isinstance(v, dict) else [prefix + key])
        ]

    assert sorted(leaves(small)) == sorted(USER_FACING) and 15 <= len(USER_FACING) <= 25
    assert set(leaves(small)) < set(leaves(full)) and full == AlignConfig().model_dump(mode="json")
    assert small["bev"]["range_m"] == 100.0 and "coarse_stride" not in small.get("mim", {})
    described = {name: f.description for name, f in type(AlignConfig().bev).model_fields.items()}
    assert "metres" in described["range_m"] and "seed" not in described["range_m"]


def test_a_saved_config_naming_retired_settings_loads_at_their_value_else_names_them(tmp_path):
    """A full dump saved before settings became constants still loads when it holds their values (the engine's
    constants); a retired setting at another value is refused in one line naming it."""
    from bb_align.engine.config import RETIRED, AlignConfig

    old = AlignConfig().model_dump(mode="json")
    for path, value in RETIRED.items():
        *sections, name = path.split(".")
        node = old
        for sec in sections:
            node = node.setdefault(sec, {})
        node[name] = list(value) if isinstance(value, tuple) else value
    old["acquire"]["top_k"] = 8
    (tmp_path / "old.json").write_text(json.dumps(old))
    runner = CliRunner()
    out = runner.invoke(app, ["config", "--check", str(tmp_path / "old.json"), "--advanced"])
    assert out.exit_code == 0, out.output
    assert json.loads(out.stdout)["acquire"]["top_k"] == 8 and "score" not in json.loads(out.stdout)["acquire"]
    for section, name, value in (("acquire", "score", "blend"), ("refine", "point_weight", 0.2)):
        (tmp_path / "moved.json").write_text(json.dumps({section: {name: value}}))
        out = runner.invoke(app, ["config", "--check", str(tmp_path / "moved.json")])
        lines = out.stderr.strip().splitlines()
        assert out.exit_code == 2 and f"{section}.{name} is no longer a setting" in out.stderr, out.output
        assert "Traceback" not in out.output and sum("no longer a setting" in line for line in lines) == 1


def test_config_check_blames_check_with_the_field_and_its_limit(tmp_path):
    (tmp_path / "bad.json").write_text(json.dumps({"bev": {"range_m": -5}}))
    (tmp_path / "typo.yaml").write_text("bev: {rang_m: 80}\n")
    (tmp_path / "broken.yaml").write_text("bev: [\n")
    runner = CliRunner()
    for name, says in (
        ("bad.json", "bev.range_m: Input should be greater than 0 (got -5)"),
        ("typo.yaml", "bev.rang_m: no such setting (did you mean bev.range_m?)"),
        ("broken.yaml", "not valid YAML"),
    ):
        out = runner.invoke(app, ["config", "--check", str(tmp_path / name)])
        assert out.exit_code == 2, out.output
        assert "--check" in out.stderr and "--config" not in out.stderr and says in out.stderr, out.stderr
        assert "Traceback" not in out.output


def test_flags_read_as_flags_in_help():
    out = CliRunner().invoke(app, ["align", "--help"])
    assert out.exit_code == 0
    assert "<bool>" not in out.stdout
    json_line = next(line for line in out.stdout.splitlines() if line.strip().startswith("--json"))
    assert json_line.split()[1] == "print"  # the help text follows the flag: no value to give


def test_help_loads_neither_numpy_nor_the_engine_nor_the_lab():
    """`bb-align --help` must stay fast: it builds the command list without importing the heavy packages (their
    import is what cost seconds of CPU)."""
    code = (
        "import sys\nfrom typer.testing import CliRunner\nfrom bb_align.cli import app\n"
        "r = CliRunner().invoke(app, ['--help'])\nassert r.exit_code == 0 and 'soak' in r.stdout, r.output\n"
        "heavy = ('numpy', 'scipy', 'numba', 'cv2', 'pydantic', 'bb_align.engine.', 'bb_align.lab.soak', "
        "'bb_align.protocol', 'zenoh', 'fastapi')\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in heavy or m.startswith(heavy)))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", out.stdout


def test_lazy_soak_command_runs_its_own_options():
    out = CliRunner().invoke(app, ["soak", "--help"])
    assert out.exit_code == 0 and "--duration" in out.stdout and "--flood-s" in out.stdout


def test_sim_pair_writes_files_align_reads_and_the_truth(tmp_path):
    out = CliRunner().invoke(app, ["sim", str(tmp_path / "pair"), "--pair", "--max-distance", "20", "--seed", "3"])
    assert out.exit_code == 0, out.output
    pair = tmp_path / "pair"
    ego, peer = load_cloud(pair / "ego.npy"), load_cloud(pair / "peer.npy")
    assert len(ego) > 1000 and len(peer) > 1000 and ego.shape[1] == 4
    assert load_boxes(pair / "ego_boxes.json").shape[1] == 7
    truth = json.loads((pair / "truth.json").read_text())
    T = np.array(truth["T_ego_peer"])
    assert abs(np.hypot(T[0, 3], T[1, 3]) - 20.0) < 3.0  # the cars are --max-distance apart
    assert np.isclose(truth["yaw_deg"], np.degrees(np.arctan2(T[1, 0], T[0, 0])), atol=1e-3)


def test_a_plot_without_the_lab_extra_stops_at_once_naming_the_extra(tmp_path):
    """matplotlib is the `lab` extra: blocked here as if not installed, `align --plot` stops before aligning."""
    np.save(tmp_path / "c.npy", np.zeros((10, 3), np.float32))
    code = (
        "import sys\nsys.modules['matplotlib'] = None\nfrom bb_align.cli import app\n"
        f"app(['align', {str(tmp_path / 'c.npy')!r}, {str(tmp_path / 'c.npy')!r}, '--plot', "
        f"{str(tmp_path / 'p.png')!r}], prog_name='bb-align')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "matplotlib" in lines[0] and "bb-align[lab]" in lines[0], out.stderr
    assert out.stdout == "" and not (tmp_path / "p.png").exists()


def test_sim_help_names_the_default_fleet_the_simulator_uses():
    """The help is written without importing the simulator; it must still say what the default is."""
    from bb_align.lab.sim.sensors import DEFAULT_FLEET

    out = CliRunner().invoke(app, ["sim", "--help"], terminal_width=200)
    assert out.exit_code == 0
    assert "[default: " + ",".join(DEFAULT_FLEET) + "]" in " ".join(out.stdout.split())
