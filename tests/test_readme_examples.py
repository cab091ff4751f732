"""The README's examples, run as written (with small sizes)."""

from __future__ import annotations

import json

import numpy as np
from typer.testing import CliRunner

from mvreg.cli import app

runner = CliRunner()


def test_make_problem_and_solve(tmp_path):
    p = tmp_path / "p.npz"
    r = runner.invoke(app, ["make-problem", "--patches", "300", "--noise", "0.01", "--out", str(p)])
    assert r.exit_code == 0, r.output
    out = tmp_path / "result.json"
    r = runner.invoke(
        app, ["solve", str(p), "--out", str(out), "--rho", "auto", "--max-iter", "500"]
    )
    assert r.exit_code == 0, r.output
    assert "certified yes" in r.output
    res = json.loads(out.read_text())
    assert res["format"] == "mvreg.poses/1" and len(res["poses"]) == 300
    assert res["certificate"]["certified"] is True
    # Errors against the ground truth written beside the problem.
    r = runner.invoke(app, ["eval", str(out), "--truth", str(tmp_path / "p_truth.json")])
    assert r.exit_code == 0, r.output
    assert "rotation median" in r.output


def test_python_api_solve():
    from data_synth.problems import make_problem
    from mvreg.solver import PatchProblem, solve

    prob, _ = make_problem(20, d=3, noise=0.0, seed=2)
    problem = PatchProblem(prob.coords, prob.patch, prob.node_ids[prob.node_index])
    result = solve(problem)
    assert result.rotations.shape == (20, 3, 3) and result.translations.shape == (20, 3)
    assert result.certificate.certified


def test_synth_register_eval_and_python_api(tmp_path):
    import mvreg

    scans = tmp_path / "scans"
    r = runner.invoke(
        app,
        [
            "synth",
            "builtin",
            "--out",
            str(scans),
            "--views",
            "8",
            "--noise",
            "0.002",
            "--seed",
            "0",
            "--points-per-scan",
            "10000",
            "--random-frames",
        ],
    )
    assert r.exit_code == 0, r.output
    out = tmp_path / "result"
    r = runner.invoke(
        app, ["register", str(scans), "--out", str(out), "--refine", "2", "--seed", "0"]
    )
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["eval", str(out), "--truth", str(scans / "ground_truth.json")])
    assert r.exit_code == 0, r.output
    report = json.loads((out / "report.json").read_text())
    diag = json.loads((scans / "ground_truth.json").read_text())["object_diagonal"]
    assert report["ground_truth_errors"]["rotation_deg_max"] < 0.5
    assert report["ground_truth_errors"]["translation_max"] < 0.005 * diag
    reg = mvreg.register(scans, seed=0, **{"refine.rounds": 2})
    assert reg.unregistered == [] and set(reg.T_world_scan) == set(report["registered"])
    assert reg.report()["format"] == "mvreg.report/1"
    a = np.stack([reg.T_world_scan[n] for n in report["registered"]])
    b = np.stack(
        [np.asarray(v) for v in json.loads((out / "poses.json").read_text())["poses"].values()]
    )
    assert np.allclose(a, b, atol=1e-9)  # same seed, same poses (API and CLI)
