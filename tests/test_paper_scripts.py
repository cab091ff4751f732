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
