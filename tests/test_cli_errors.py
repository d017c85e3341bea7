"""One error style for every bad input the CLI takes: `bb-align: WHAT: problem` on stderr, one line, exit code 2, no
usage block and no traceback (usage stays for a wrong command or option name). Runs the real command (typer's
CliRunner, a subprocess where the process itself matters)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from bb_align.cli import app

REPO = Path(__file__).resolve().parents[1]


def _one_line_refusal(out, *says: str) -> str:
    assert out.exit_code == 2, out.output
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("bb-align"), out.stderr
    assert "Usage:" not in out.output and "Traceback" not in out.output and "validation error" not in out.output
    for s in says:
        assert s in lines[0], (s, lines[0])
    return lines[0]


@pytest.fixture
def cloud(tmp_path):
    path = tmp_path / "cloud.npy"
    np.save(path, np.random.default_rng(0).uniform(-20, 20, (500, 3)).astype(np.float32))
    return path


def test_missing_files_and_bad_folders_are_one_line(tmp_path, cloud):
    runner = CliRunner()
    cases = [
        (["align", str(tmp_path / "nope.npy"), str(cloud)], ("ego_cloud", "nope.npy", "does not exist")),
        (["align", str(cloud), str(cloud), "--ego-boxes", str(tmp_path / "b.json")], ("--ego-boxes", "b.json")),
        (["align", str(cloud), str(cloud), "--config", str(tmp_path / "c.json")], ("--config", "does not exist")),
        (["recover", str(tmp_path / "no_root"), str(tmp_path / "out")], ("root", "no_root", "does not exist")),
        (["recover", str(cloud), str(tmp_path / "out")], ("root", "cloud.npy", "is a file")),
        (["eval", str(tmp_path / "no_root")], ("no_root",)),
        (["align", str(cloud), str(cloud), "--range-m", "wide"], ("--range-m", "number")),
    ]
    for args, says in cases:
        _one_line_refusal(runner.invoke(app, args), *says)


def test_a_wrong_command_or_option_name_still_shows_usage(cloud):
    runner = CliRunner()
    for args in (["alig"], ["align", str(cloud), str(cloud), "--bogus"], ["align", str(cloud)]):
        out = runner.invoke(app, args)
        assert out.exit_code == 2 and "Usage:" in out.output, out.output


def test_a_config_key_typo_names_the_nearest_valid_key(tmp_path, cloud):
    (tmp_path / "typo.json").write_text('{"bev": {"range_mm": 60}}')
    (tmp_path / "typo.yaml").write_text("prior:\n  max_yaw_dg: 5\n")
    runner = CliRunner()
    out = runner.invoke(app, ["align", str(cloud), str(cloud), "--config", str(tmp_path / "typo.json")])
    _one_line_refusal(out, "--config", "bev.range_mm: no such setting (did you mean bev.range_m?)")
    out = runner.invoke(app, ["config", "--check", str(tmp_path / "typo.yaml")])
    _one_line_refusal(out, "--check", "prior.max_yaw_dg: no such setting (did you mean prior.max_yaw_deg?)")


@pytest.mark.parametrize(
    "text, says",
    [
        ("1 0 0\n0 1 0\n", "got a 2x3 matrix; expected a 4x4 rigid transform"),
        ("1 0 0 5\n0 1 0 0\n0 0 1 0\n", "got a 3x4 matrix"),
        # A 3x3 rotation (3-D, no translation) given where the ground-plane form is read: say which shape is wanted.
        ("0.8 -0.6 0\n0.6 0.8 0\n0 0.1 0.995\n", "a 3x3 rotation alone is not a prior"),
        ("2 0 0 1\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "top-left 3x3 block is not a rotation"),
        ("a b c\n", "not a plain-text matrix"),
        ("1 0 0\n0 1 0\n0 0 nan\n", "holds NaN or inf"),
    ],
)
def test_a_bad_prior_says_what_shape_is_expected(tmp_path, cloud, text, says):
    (tmp_path / "prior.txt").write_text(text)
    out = CliRunner().invoke(app, ["align", str(cloud), str(cloud), "--prior", str(tmp_path / "prior.txt")])
    line = _one_line_refusal(out, "--prior", "prior.txt", says)
    assert "3x3 ground-plane one [cos -sin tx; sin cos ty; 0 0 1]" in line


def test_an_empty_or_all_nan_cloud_is_bad_input_not_a_failed_alignment(tmp_path, cloud):
    np.save(tmp_path / "empty.npy", np.zeros((0, 3), np.float32))
    np.save(tmp_path / "nan.npy", np.full((50, 4), np.nan, np.float32))
    runner = CliRunner()
    for name in ("empty.npy", "nan.npy"):
        out = runner.invoke(app, ["align", str(cloud), str(tmp_path / name)])
        _one_line_refusal(out, name, "no point with a finite x, y, z")
        assert out.stdout == ""


def test_an_environment_variable_typo_is_named_with_the_nearest_valid_one(monkeypatch):
    from bb_align.server import commands

    for k in list(os.environ):
        if k.startswith("BBALIGN_"):
            monkeypatch.delenv(k)
    started = []
    monkeypatch.setattr(commands, "run_server", lambda settings, log_level="info": started.append(settings))
    runner = CliRunner()
    cases = {
        "BBALIGN_ALIGN__BEV__RANGE_MM": "BBALIGN_ALIGN__BEV__RANGE_MM: no such setting (did you mean "
        "BBALIGN_ALIGN__BEV__RANGE_M?)",
        "BBALIGN_LIMITS__REPLAYY": "(did you mean BBALIGN_LIMITS__REPLAY?)",
        "BBALIGN_PROT": "BBALIGN_PROT: no such setting (did you mean BBALIGN_PORT?)",
    }
    for var, says in cases.items():
        out = runner.invoke(app, ["serve", "--demo", "--no-zenoh"], env={var: "3"})
        _one_line_refusal(out, says)
    out = runner.invoke(app, ["serve", "--demo", "--no-zenoh"], env={"BBALIGN_ALIGN__BEV__RANGE_M": "-5"})
    _one_line_refusal(out, "BBALIGN_ALIGN__BEV__RANGE_M: Input should be greater than 0 (got '-5')")
    assert started == []  # nothing started on a bad setting


def test_a_reader_that_goes_away_ends_the_command_quietly():
    """`bb-align ... | head -1`: the pipe's reader is gone before the command writes; it exits 0, says nothing."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "service"), str(REPO / "client")])}
    r, w = os.pipe()
    os.close(r)  # no reader: the first write fails with EPIPE
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "bb_align", "config", "--dump", "--advanced"],
            stdout=w,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            timeout=60,
        )
    finally:
        os.close(w)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
