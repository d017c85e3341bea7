"""The README stays true by construction: its quick start's `bb-align` commands, taken from the README itself, are
run as written (in a scratch folder) and what they print is checked against the numbers the README shows, within
the rounding the README states; the benchmarks write under out/ unless asked to record into docs/."""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from bb_align.cli import app
from bb_align.engine.geometry import pose_error
from readme_support import quickstart_tolerance

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()
NUMBER = r"(-?\d+(?:\.\d+)?)"


def _section(title: str) -> str:
    start = README.index(f"## {title}\n")
    end = README.index("\n## ", start + 1)
    return README[start:end]


def _blocks(text: str, lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", text, re.S)


def _quick_start_commands() -> list[list[str]]:
    """Every `bb-align sim|align` command of the quick start's shell block, continuation lines joined."""
    (shell, *_) = _blocks(_section("Quick start"), "bash")
    joined = re.sub(r"\\\n\s*", " ", shell)
    commands = []
    for line in joined.splitlines():
        words = shlex.split(line.split("#", 1)[0])
        if words[:1] == ["bb-align"] and words[1] in ("sim", "align"):
            commands.append(words[1:])
    return commands


def _printed_pose(text: str) -> dict[str, float]:
    m = re.search(
        rf"success: yaw {NUMBER} deg, tx {NUMBER} m, ty {NUMBER} m, inliers_bv (\d+)/(\d+), inliers_box (\d+)", text
    )
    assert m, text
    s = re.search(rf"1-sigma: translation {NUMBER} m / {NUMBER} m \(best / worst direction\), yaw {NUMBER} deg", text)
    assert s, text
    keys = ("yaw", "tx", "ty", "inliers_bv", "matches_bv", "inliers_box", "sigma_best", "sigma_worst", "sigma_yaw")
    return dict(zip(keys, map(float, m.groups() + s.groups()), strict=True))


def test_the_quick_start_prints_the_numbers_the_readme_shows(tmp_path, monkeypatch):
    quick = _section("Quick start")
    commands = _quick_start_commands()
    assert [c[0] for c in commands] == ["sim", "align"], commands
    (shown,) = _blocks(quick, "text")
    tol_deg, tol_m, tol_inliers = quickstart_tolerance(quick)

    monkeypatch.chdir(tmp_path)  # the commands write out/sample, relative, as a user's checkout would
    runner = CliRunner()
    for args in commands:
        out = runner.invoke(app, args)
        assert out.exit_code == 0, (args, out.output)
    got, want = _printed_pose(out.stdout), _printed_pose(shown)
    assert abs(got["yaw"] - want["yaw"]) <= tol_deg and abs(got["sigma_yaw"] - want["sigma_yaw"]) <= tol_deg
    for k in ("tx", "ty", "sigma_best", "sigma_worst"):
        assert abs(got[k] - want[k]) <= tol_m, (k, got[k], want[k])
    assert got["matches_bv"] == want["matches_bv"]
    for k in ("inliers_bv", "inliers_box"):
        assert abs(got[k] - want[k]) <= tol_inliers * want[k], (k, got[k], want[k])

    # "truth.json says yaw Y deg, tx X m, ty Y m: E m and F deg off."
    m = re.search(
        rf"`truth.json` says yaw {NUMBER} deg, tx {NUMBER} m, ty {NUMBER} m: {NUMBER} m and {NUMBER} deg off", quick
    )
    assert m, "the README compares the answer with truth.json"
    truth = json.loads((tmp_path / "out" / "sample" / "truth.json").read_text())
    assert [truth["yaw_deg"], truth["tx"], truth["ty"]] == pytest.approx([float(v) for v in m.groups()[:3]], abs=5e-4)
    T = re.search(r"T_ego_peer =\n((?:\s+\S+){16})", out.stdout)
    t_err, r_err = pose_error(np.array(T.group(1).split(), float).reshape(4, 4), np.asarray(truth["T_ego_peer"]))
    assert abs(t_err - float(m.group(4))) <= tol_m and abs(r_err - float(m.group(5))) <= tol_deg


def test_benchmarks_write_under_out_unless_asked_to_record():
    from bb_align.lab.recording import output_path

    assert output_path("docs/real_pairs") == Path("out/real_pairs")
    assert output_path("docs/real_pairs", record=True) == Path("docs/real_pairs")
    for script in sorted((REPO / "benchmarks").glob("*.py")):
        text = script.read_text()
        assert not re.search(r"default=Path\(\"docs|typer\.Option\(\s*Path\(\"docs", text), script.name
    if shutil.which("make") is None:
        pytest.skip("no make on this machine")
    targets = ["bench-accuracy", "bench-real", "bench-sim-real", "bench-sim-places", "bench-flood"]

    def dry_run(*extra: str) -> list[str]:
        r = subprocess.run(["make", "-n", *targets, *extra], cwd=REPO, capture_output=True, text=True, timeout=60)
        assert r.returncode == 0, r.stderr
        commands = re.sub(r"\\\n\s*", " ", r.stdout).splitlines()  # continuation lines joined
        return [line for line in commands if "bb-align" in line or "benchmarks/" in line]

    plain = dry_run()
    assert plain and not [line for line in plain if "docs/" in line], plain  # git status stays clean
    recorded = dry_run("RECORD=1")
    assert any("--out docs/real_pairs" in line for line in recorded)
    assert any("docs/accuracy/summary.json" in line for line in recorded)
    assert sum(bool(re.search(r"--record(\s|$)", line)) for line in recorded) == 2  # sim_vs_real, sim_places
