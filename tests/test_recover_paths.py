"""`bb-align recover` reads only inside ROOT and writes only inside OUT: paths a dataset names (DAIR's
data_info.json) are resolved and refused when they leave ROOT, symbolic links out of ROOT are refused, and the
refusal is one line with exit code 2. The hostile datasets are built here, in tmp_path."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from bb_align.cli import app
from bb_align.io.dair import COOP_DIR, DairFrameFiles, write_dair_root
from bb_align.io.dataset import x_to_world


def _digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and not p.is_symlink()
    }


def _dair(tmp_path: Path) -> Path:
    """A one-frame DAIR-V2X-C root at tmp_path/root (its cooperative folder returned)."""
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-20, 20, (500, 3)), rng.uniform(0, 1, 500)]).astype(np.float32)
    boxes = np.array([[5.0, 1.0, -1.0, 4.5, 1.9, 1.6, 0.2]])
    T = x_to_world([10.0, 2.0, -0.4, 0.5, 20.0, -0.5])
    return write_dair_root(tmp_path / "root", [DairFrameFiles("000001", "000007", pts, pts[:300], boxes, boxes, T)])


def _set_entry(base: Path, **paths) -> None:
    info_path = base / "cooperative" / "data_info.json"
    info = json.loads(info_path.read_text())
    info[0].update(paths)
    info_path.write_text(json.dumps(info))


def _refused(args, *says) -> None:
    r = CliRunner().invoke(app, args)
    lines = r.stderr.strip().splitlines()
    assert r.exit_code == 2 and len(lines) == 1 and lines[0].startswith("bb-align"), r.output
    assert "Traceback" not in r.output and "Usage:" not in r.output
    for s in says:
        assert s in lines[0], (s, lines[0])


@pytest.mark.parametrize(
    "key, value",
    [
        ("calib_lidar_i2v_path", "../../../evil.json"),  # leaves ROOT: would overwrite beside it, write outside OUT
        ("calib_lidar_i2v_path", "cooperative/../../../evil.json"),
        ("vehicle_pointcloud_path", "/etc/hostname"),
        ("infrastructure_pointcloud_path", "../../secret.pcd"),
    ],
)
def test_a_path_in_data_info_that_leaves_root_is_refused(tmp_path, key, value):
    base = _dair(tmp_path)
    (tmp_path / "evil.json").write_text('{"mine": 1}')
    _set_entry(base, **{key: value})
    before, beside = _digest(tmp_path / "root"), (tmp_path / "evil.json").read_text()
    _refused(["recover", str(tmp_path / "root"), str(tmp_path / "out"), "--quiet"], key, "outside")
    assert _digest(tmp_path / "root") == before and (tmp_path / "evil.json").read_text() == beside
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").rglob("*.pcd"))


def test_a_dotted_path_that_stays_inside_root_is_written_inside_out(tmp_path):
    """The issue's case, in the form that is legitimate: `..` that comes back into ROOT. ROOT's own calibration is
    not overwritten; the recovered one lands at its normal place in OUT and nowhere else."""
    base = _dair(tmp_path)
    calib = base / "cooperative" / "calib" / "lidar_i2v" / "000001.json"
    _set_entry(base, calib_lidar_i2v_path=f"../{COOP_DIR}/cooperative/calib/lidar_i2v/000001.json")
    before = _digest(tmp_path / "root")
    out = tmp_path / "out"
    r = CliRunner().invoke(app, ["recover", str(tmp_path / "root"), str(out), "--quiet"])
    assert r.exit_code == 0, r.output
    assert _digest(tmp_path / "root") == before
    written = out / calib.relative_to(tmp_path / "root")
    assert written.is_file() and {p.name for p in tmp_path.iterdir()} == {"root", "out"}
    row = json.loads((out / "recovered_poses.jsonl").read_text().splitlines()[0])
    assert row["lidar_i2v"] == "cooperative/calib/lidar_i2v/000001.json"


def test_a_symlink_out_of_root_is_refused_and_its_target_never_copied(tmp_path):
    base = _dair(tmp_path)
    secret = tmp_path / "secret.txt"
    secret.write_text("private key material")
    (base / "vehicle-side" / "notes.txt").symlink_to(secret)
    _refused(["recover", str(tmp_path / "root"), str(tmp_path / "out"), "--quiet"], "notes.txt", "symbolic link")
    copied = [p for p in (tmp_path / "out").rglob("*") if p.is_file()] if (tmp_path / "out").exists() else []
    assert all("private key material" not in p.read_text(errors="ignore") for p in copied)
    # a linked folder out of ROOT is refused the same way (the reader would follow it)
    (base / "vehicle-side" / "notes.txt").unlink()
    (tmp_path / "elsewhere").mkdir()
    (base / "vehicle-side" / "extra").symlink_to(tmp_path / "elsewhere", target_is_directory=True)
    _refused(["recover", str(tmp_path / "root"), str(tmp_path / "out2"), "--quiet"], "extra", "symbolic link")


def test_a_symlink_in_an_opv2v_root_is_refused_and_one_inside_root_is_kept(tmp_path):
    root = tmp_path / "root"
    for agent in ("0", "1"):
        d = root / "scenario" / agent
        d.mkdir(parents=True)
        (d / "000000.yaml").write_text("lidar_pose: [0, 0, 0, 0, 0, 0]\n")
        np.save(d / "000000.npy", np.zeros((10, 3), np.float32))
    secret = tmp_path / "secret.txt"
    secret.write_text("private")
    (root / "scenario" / "0" / "000000.pcd").symlink_to(secret)
    _refused(["recover", str(root), str(tmp_path / "out"), "--quiet"], "000000.pcd", "symbolic link")
    # OUT planted with a link out of it (a resumed run's folder): nothing is written through it
    os.unlink(root / "scenario" / "0" / "000000.pcd")
    (root / "scenario" / "readme.txt").write_text("inside")
    (root / "scenario" / "readme_link.txt").symlink_to(root / "scenario" / "readme.txt")
    from bb_align.io.recover import _check_paths, _out_path

    root_r, out_r = _check_paths(root, tmp_path / "out")  # a link that stays inside ROOT is fine
    assert _out_path(out_r, root_r, root_r / "scenario" / "readme_link.txt") == out_r / "scenario" / "readme_link.txt"
    out_r.mkdir()
    (out_r / "scenario").symlink_to(tmp_path, target_is_directory=True)
    with pytest.raises(ValueError, match="outside OUT"):
        _out_path(out_r, root_r, root_r / "scenario" / "readme.txt")
