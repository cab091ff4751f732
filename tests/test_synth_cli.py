"""``synth_command`` as the lead registers it: ``app.command("synth")(synth_command)``."""

from __future__ import annotations

import json

import pytest
import typer
from typer.testing import CliRunner

from mvreg.cli.synth import synth_command
from mvreg.io.poses import read_poses_json

app = typer.Typer(add_completion=False, pretty_exceptions_enable=False)
app.command("synth")(synth_command)


@app.command("noop")
def _noop():  # a second command, so "synth" stays a subcommand as in mvreg
    """Placeholder."""


runner = CliRunner()


def test_synth_builtin_writes_scans_and_ground_truth(tmp_path):
    out = tmp_path / "scans"
    args = ["synth", "builtin", "--out", str(out), "--views", "3", "--points-per-scan", "800"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "wrote 3 scans" in result.output
    assert sorted(read_poses_json(out / "ground_truth.json")) == [
        "scan_000.ply",
        "scan_001.ply",
        "scan_002.ply",
    ]
    synth = json.loads((out / "synth.json").read_text())
    assert synth["seed"] == 0 and synth["parameters"]["noise"] == 0.002

    # A non-empty folder is refused without --force: one line, exit code 2.
    result = runner.invoke(app, args)
    assert result.exit_code == 2
    assert "not empty" in result.output and "--force" in result.output
    assert "Traceback" not in result.output
    result = runner.invoke(app, [*args, "--force", "--scanner", "lidar", "--random-frames"])
    assert result.exit_code == 0, result.output


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--views", "0"], "views must be"),
        (["--noise", "-0.1"], "noise must be"),
        (["--outliers", "2"], "outliers fraction must be"),
        (["--placement", "explicit"], "needs --viewpoints"),
    ],
)
def test_absurd_parameters_exit_2(tmp_path, extra, message):
    result = runner.invoke(app, ["synth", "builtin", "--out", str(tmp_path / "o"), *extra])
    assert result.exit_code == 2
    assert message in result.output
    assert not (tmp_path / "o").exists()


def test_bad_mesh_exit_2_naming_the_file(tmp_path):
    notes = tmp_path / "notes.txt"
    notes.write_text("not a mesh")
    for path in [tmp_path / "missing.obj", notes]:
        result = runner.invoke(app, ["synth", str(path), "--out", str(tmp_path / "o")])
        assert result.exit_code == 2
        assert path.name in result.output


def test_explicit_viewpoints_file(tmp_path):
    viewpoints = tmp_path / "views.txt"
    viewpoints.write_text("2 0 0\n0 2 0\n0 0 2\n-2 0 0\n")
    out = tmp_path / "o"
    args = ["synth", "builtin", "--out", str(out), "--viewpoints", str(viewpoints)]
    result = runner.invoke(app, [*args, "--points-per-scan", "500"])
    assert result.exit_code == 0, result.output
    assert len(read_poses_json(out / "ground_truth.json")) == 4


def test_sequence_mode(tmp_path):
    out = tmp_path / "seq"
    args = ["synth", "builtin", "--out", str(out), "--sequence", "--views", "3"]
    result = runner.invoke(app, [*args, "--points-per-scan", "1000"])
    assert result.exit_code == 0, result.output
    assert (out / "timestamps.txt").read_text().split() == ["0.0", "0.1", "0.2"]
    result = runner.invoke(app, [*args, "--force", "--scanner", "pinhole"])
    assert result.exit_code == 2 and "LiDAR" in result.output


def test_help_has_examples():
    result = runner.invoke(app, ["synth", "--help"])
    assert result.exit_code == 0
    assert "mvreg synth builtin --out" in result.output
