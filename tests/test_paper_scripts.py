"""Smoke tests of the paper-experiment and benchmark scripts (issue 5): --quick --out tmp."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

SCRIPTS = {
    "paper000_fig2.py": "paper000_fig2",
    "paper000_fig3.py": "paper000_fig3",
    "paper001_fig1.py": "paper001_fig1",
    "bench_solvers.py": "solvers",
}


@pytest.mark.parametrize("script", sorted(SCRIPTS))
def test_script_quick(script, tmp_path):
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    p = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / script), "--quick", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
        env=env,
    )
    assert p.returncode == 0, p.stderr[-2000:]
    stem = SCRIPTS[script]
    md, png = tmp_path / f"{stem}.md", tmp_path / f"{stem}.png"
    assert md.is_file() and png.is_file()
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000
    text = md.read_text()
    # A markdown table: a header row followed by its separator row, then data rows.
    lines = text.splitlines()
    seps = [i for i, line in enumerate(lines) if line.startswith("| ---")]
    assert seps, text[:500]
    assert lines[seps[0] - 1].startswith("| ") and lines[seps[0] + 1].startswith("| ")
    # Reproducibility header: machine, command, BLAS threads, date.
    for key in ("os.cpu_count()", "command:", "OPENBLAS_NUM_THREADS=1", "date:", "memory"):
        assert key in text, key
    assert f"{png.name}" in text
    assert "Observations" in text


# --------------------------------------------------------------------------- public API only


def _mvreg_api_violations(path: Path) -> list[str]:
    """Private mvreg names imported or read, mvreg module attributes assigned or deleted
    (monkeypatching), and sys.path changes, in one file (AST, no import)."""
    import ast

    tree = ast.parse(path.read_text(), filename=str(path))
    out: list[str] = []
    modules: set[str] = set()  # local names bound to mvreg modules

    def private(dotted: str) -> bool:
        return any(p.startswith("_") and not p.startswith("__") for p in dotted.split("."))

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "mvreg":
                    if private(a.name):
                        out.append(f"{path.name}:{node.lineno}: import {a.name}")
                    modules.add(a.asname or a.name.split(".")[0])
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "mvreg":
            for a in node.names:
                if private(f"{node.module}.{a.name}"):
                    out.append(f"{path.name}:{node.lineno}: from {node.module} import {a.name}")
                modules.add(a.asname or a.name)  # a module or not: never to be assigned to

    def on_mvreg(expr) -> bool:
        while isinstance(expr, ast.Attribute):
            expr = expr.value
        return isinstance(expr, ast.Name) and expr.id in modules

    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and on_mvreg(node.value):
            if private(node.attr):
                out.append(f"{path.name}:{node.lineno}: reads {node.attr}")
            if isinstance(node.ctx, (ast.Store, ast.Del)):
                out.append(f"{path.name}:{node.lineno}: assigns {node.attr} of an mvreg module")
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
            if node.func.id in ("setattr", "delattr") and node.args and on_mvreg(node.args[0]):
                out.append(f"{path.name}:{node.lineno}: {node.func.id} on an mvreg module")
        if isinstance(node, ast.Attribute) and node.attr == "path" and path.parts[-2] != "scripts":
            if isinstance(node.value, ast.Name) and node.value.id == "sys":
                out.append(f"{path.name}:{node.lineno}: sys.path in the bench package")
    return out


def test_bench_and_scripts_use_only_public_mvreg_names():
    files = sorted((ROOT / "bench").rglob("*.py")) + sorted((ROOT / "scripts").glob("*.py"))
    assert len(files) > 10
    bad = [v for f in files for v in _mvreg_api_violations(f)]
    assert not bad, "\n".join(bad)


def test_public_api_check_catches_private_imports_and_monkeypatching(tmp_path):
    (tmp_path / "scripts").mkdir()
    f = tmp_path / "scripts" / "old.py"
    f.write_text(
        "import mvreg.pipeline as pl\n"
        "from mvreg.pairwise.align import _decide\n"
        "from mvreg import pipeline\n"
        "pl.align_pairs = lambda *a: []\n"
        "setattr(pipeline, 'load_source', None)\n"
        "x = pl._evaluate\n"
    )
    got = _mvreg_api_violations(f)
    assert len(got) == 4, got
