"""Helpers every benchmark shares: paths, the machine description, the bunny's truth.

- :data:`ROOT` -- the repository (``docs/benchmarks`` is the default output folder);
  :data:`SHARED` -- ``../shared/data`` beside it (meshes, the Stanford bunny scans).
- :func:`machine` -- one line: CPU, cores, memory, Python, load average.
- :func:`machine_info` -- the reproducibility header of the paper scripts (markdown bullets:
  date, command, machine, versions, BLAS threads).
- :func:`bunny_truth` -- ``T_world_scan`` per scan name from the bunny's ``bun.conf``.
"""

from __future__ import annotations

import datetime
import os
import platform
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
BUNNY = SHARED / "stanford_bunny_scans"


def machine() -> str:
    """CPU model, cores, memory, Python version and the load average, on one line."""
    mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    return (
        f"{cpu}, {os.cpu_count()} cores, {mem:.0f} GiB RAM, Python {platform.python_version()}; "
        f"load average at report time {load} (other jobs were running: times are upper bounds)"
    )


def blas_threads() -> str:
    """The BLAS libraries threadpoolctl sees and their thread counts."""
    try:
        from threadpoolctl import threadpool_info

        return ", ".join(
            f"{i.get('internal_api')} {i.get('num_threads')} thread(s)"
            for i in threadpool_info()
            if i.get("user_api") == "blas"
        )
    except Exception:  # pragma: no cover - threadpoolctl is optional here
        return "unknown"


def machine_info(blas: str) -> list[str]:
    """Markdown bullets: date, command, machine, Python/numpy/scipy, then ``- BLAS threads:
    OPENBLAS_NUM_THREADS=<env> `` followed by ``blas`` (the caller's note on threads)."""
    mem = "unknown"
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                mem = f"{int(line.split()[1]) / 1024**2:.1f} GiB"
    except OSError:
        pass
    import scipy

    return [
        f"- date: {datetime.datetime.now().isoformat(timespec='seconds')}",
        f"- command: `{' '.join([Path(sys.executable).name, *sys.argv])}`",
        f"- machine: {platform.platform()}, {platform.processor() or platform.machine()}, "
        f"os.cpu_count() = {os.cpu_count()}, memory {mem}",
        f"- python {platform.python_version()}, numpy {np.__version__}, scipy {scipy.__version__}",
        f"- BLAS threads: OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')} {blas}",
    ]


def bunny_truth(folder: Path = BUNNY) -> dict[str, np.ndarray]:
    """bun.conf: p_world = R(q)^T p + t, q = (qx, qy, qz, qw)."""
    from scipy.spatial.transform import Rotation

    truth = {}
    for line in (Path(folder) / "bun.conf").read_text().splitlines():
        p = line.split()
        if p and p[0] == "bmesh":
            T = np.eye(4)
            T[:3, :3] = Rotation.from_quat([float(v) for v in p[5:9]]).as_matrix().T
            T[:3, 3] = [float(v) for v in p[2:5]]
            truth[p[1]] = T
    return truth
