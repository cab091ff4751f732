"""Cases the hostile-input corpus (``scripts/bad_input_corpus.py``) found BAD or POOR,
each kept here as a regression test: exit code, culprit named, inputs untouched."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from mvreg.cli import app
from mvreg.errors import InputError, ScanFileError
from tests.test_bad_input import GOOD, ply_header, register_args

runner = CliRunner()


def good_folder(tmp: Path) -> Path:
    d = tmp / "scans"
    d.mkdir()
    np.save(d / "a.npy", GOOD)
    np.save(d / "b.npy", GOOD[::-1] + 0.01)
    return d


def digest(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.iterdir() if p.is_file()}


def one_error_line(out: str, *needles: str) -> None:
    assert "Traceback" not in out, out
    errors = [line for line in out.splitlines() if line.startswith("mvreg: error")]
    assert len(errors) == 1, out
    for needle in needles:
        assert needle in errors[0], (needle, out)


# ---------------------------------------------------------------- --rrd onto an input
@pytest.mark.parametrize("force", [False, True])
@pytest.mark.parametrize("target", ["a.npy", "sub/new.rrd", "."])
def test_rrd_inside_the_input_is_refused_even_with_force(tmp_path, force, target):
    d = good_folder(tmp_path)
    (d / "sub").mkdir()
    before = digest(d)
    rrd = d / target
    args = ["register", str(d), "--out", str(tmp_path / "out"), "--rrd", str(rrd)]
    r = runner.invoke(app, args + ["--force"] * force)
    assert r.exit_code == 2, r.output
    one_error_line(r.output, "--rrd")
    assert digest(d) == before
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------- misread binary bodies
def _binary_ply(body: bytes, n: int, fmt: str) -> bytes:
    return ply_header(n, fmt, "double").encode() + body


@pytest.mark.parametrize("kind", ["random-body", "swapped-endianness"])
def test_a_misread_binary_body_is_refused_naming_the_file(tmp_path, kind):
    d = good_folder(tmp_path)
    pts = GOOD * 0.1 + [0.3, -0.2, 1.5]
    if kind == "random-body":
        body = np.random.default_rng(3).bytes(pts.size * 8)
        data = _binary_ply(body, len(pts), "binary_little_endian")
    else:  # little-endian doubles declared big-endian
        data = _binary_ply(pts.astype("<f8").tobytes(), len(pts), "binary_big_endian")
    (d / "bad.ply").write_bytes(data)
    r = runner.invoke(app, register_args(tmp_path, d))
    assert r.exit_code == 2, r.output
    one_error_line(r.output, "bad.ply", "not a sampled surface")
    assert "RuntimeWarning" not in r.output


def test_spacing_check_keeps_real_scales(tmp_path):
    """A surface in micrometres or at 1e6 (georeferenced) passes; the rule is a ratio."""
    from mvreg.io.loaders import Scan
    from mvreg.pipeline.load import check_spacing

    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(size=(5000, 2)), np.zeros(5000)]
    for scale, offset in ((1e-6, 0.0), (1.0, 5e6), (1e3, 0.0)):
        s = Scan(name="s", path=Path("s.ply"), points=plane * scale + offset)
        assert check_spacing(s) is s
    # what misread bytes look like: magnitudes spread over orders of magnitude
    for decades in (300, 30):
        wild = rng.choice([-1, 1], (5000, 3)) * 10 ** rng.uniform(-decades, decades, (5000, 3))
        with pytest.raises(ScanFileError, match="not a sampled surface"):
            check_spacing(Scan(name="s", path=Path("s.ply"), points=wild))


# ---------------------------------------------------------------- absurd problem sizes
def test_make_problem_too_large_is_refused_before_allocating(tmp_path):
    from data_synth.problems import make_problem

    out = tmp_path / "p.npz"
    r = runner.invoke(app, ["make-problem", "--patches", str(10**12), "--out", str(out)])
    assert r.exit_code == 2, r.output
    one_error_line(r.output, "--patches 1000000000000", "GiB")
    assert not out.exists()
    with pytest.raises(InputError, match="--patches"):
        make_problem(10**9, nodes_per_pair=20)

