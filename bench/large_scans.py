"""Few large scans (issue 14): 15 builtin-object scans of 40k points each.

The data: ``mvreg synth builtin --views 15 --points-per-scan 40000 --seed 1`` (made once
into ``--data``, reused). Measured:

1. the whole ``mvreg register DIR --out OUT --seed 0 --force`` command as a user runs it
   (recording and every output written), ``--repeats`` times: wall time of the process,
   its peak memory, its report's stage times;
2. Open3D's multiway registration as its tutorial and reconstruction system teach it
   (:func:`bench.peers.open3d.run_open3d_own`: FPFH + RANSAC and point-to-plane ICP on
   every pair, pose graph, ``global_optimization``), tuned to these scans by giving it
   mvreg's own voxel size; its pairwise and global seconds (in-process, loading
   excluded).

Errors of both against the ground truth are computed the same way here
(:func:`mvreg.metrics.pose_errors`: gauge-free rotation, and translation at each scan's
centroid in % of the object's diagonal).

Writes docs/benchmarks/large_scans.md and large_scans.json.

    python scripts/bench_large_scans.py                 # 3 repeats
    python scripts/bench_large_scans.py --repeats 1 --skip-open3d
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import ROOT, machine
from bench.scale import register, synth_builtin

VIEWS, POINTS = 15, 40000


@functools.cache
def _truth(folder: Path) -> tuple[dict, dict, list, float]:
    """(truth poses, scan centroids, names in order, object diagonal) of the data, read once."""
    from mvreg.io.loaders import load_scan
    from mvreg.io.poses import read_poses_json

    truth = read_poses_json(folder / "ground_truth.json")
    names = sorted(truth)
    pts = {n: load_scan(folder / n).points for n in names}
    world = np.concatenate([p @ truth[n][:3, :3].T + truth[n][:3, 3] for n, p in pts.items()])
    diag = float(np.linalg.norm(world.max(0) - world.min(0)))  # the scans cover the object
    return truth, {n: p.mean(0) for n, p in pts.items()}, names, diag


def _errors(T_named: dict, folder: Path) -> dict:
    """Gauge-free errors of the registered scans: rotation (deg), translation at each
    scan's centroid (% of the object diagonal)."""
    from mvreg.metrics import pose_errors

    truth, centroid, names, diag = _truth(folder)
    got = [n for n in names if n in T_named]
    out = {"registered": len(got), "scans": len(names), "diagonal": diag}
    if len(got) >= 2:
        e = pose_errors(
            np.stack([T_named[n] for n in got]),
            np.stack([truth[n] for n in got]),
            at=np.stack([centroid[n] for n in got]),
        )
        out |= {
            "rot_max": float(np.max(e.rotation_deg)),
            "rot_med": float(np.median(e.rotation_deg)),
            "tr_max": 100.0 * float(np.max(e.translation)) / diag,
        }
    return out


def run_mvreg(folder: Path, repeats: int) -> dict:
    from mvreg.io.poses import read_poses_json

    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(repeats):
            out = Path(tmp) / f"out{k}"
            row = register(folder, out, ["--seed", "0"], rrd=True)
            if "error" in row:
                raise SystemExit(f"mvreg register failed: {row['error']}")
            row["errors"] = _errors(read_poses_json(out / "poses.json"), folder)
            row["voxel"] = json.loads((out / "report.json").read_text())["voxel_size"]
            runs.append(row)
            print(f"  mvreg run {k + 1}: {row['wall']:.2f} s wall, {row['registered']} registered")
    return {"runs": runs, "median_wall": statistics.median(r["wall"] for r in runs)}


def run_open3d(folder: Path, voxel: float) -> dict:
    from bench.peers.open3d import run_open3d_own
    from mvreg.io.loaders import load_scan

    names = sorted(p.name for p in folder.glob("scan_*.ply"))
    points = [load_scan(folder / n).points for n in names]
    t0 = time.perf_counter()
    o3 = run_open3d_own(points, voxel, 0)
    wall = time.perf_counter() - t0
    T = {names[k]: M for k, M in o3["T"].items()}
    row = {"pairwise_s": o3["pairwise_s"], "global_s": o3["global_s"], "edges": o3["edges"]}
    print(f"  open3d: {o3['pairwise_s']:.1f} + {o3['global_s']:.2f} s")
    return row | {"wall_in_process": wall, "errors": _errors(T, folder)}


def write_report(a, folder: Path, mv: dict, o3: dict | None) -> None:
    first = mv["runs"][0]
    walls = " / ".join(f"{r['wall']:.2f}" for r in mv["runs"])
    t = first["timings"]
    stages = ", ".join(
        f"{k} {t[k]:.2f}"
        for k in ("load", "preprocess", "pairwise", "tracks_and_solve", "robust", "refine",
                  "verification", "total")
        if k in t
    )  # fmt: skip

    def err(e):
        return (
            f"{e['registered']}/{e['scans']} | {e.get('rot_max', float('nan')):.3f} | "
            f"{e.get('rot_med', float('nan')):.3f} | {e.get('tr_max', float('nan')):.3f}"
        )

    lines = [
        "# Few large scans: 15 builtin-object scans of 40k points (issue 14)",
        "",
        f"- Command: `python scripts/bench_large_scans.py --repeats {a.repeats}"
        + (" --skip-open3d" if a.skip_open3d else "")
        + f"` ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())})",
        f"- Machine: {machine()}",
        f"- Data: `mvreg synth builtin --views {VIEWS} --points-per-scan {POINTS} --seed 1` "
        f"({folder.name}); errors gauge-free against its ground truth, translation at the "
        "scan centroids in % of the object diagonal, the same code for both methods "
        "(`mvreg.metrics.pose_errors`).",
        "- mvreg: the whole `mvreg register DIR --out OUT --seed 0` process (start-up, "
        "recording and every output included), `OPENBLAS_NUM_THREADS=1`.",
        "- Open3D: multiway registration as its tutorial teaches it, every pair, at mvreg's "
        "voxel size; in-process seconds, loading excluded.",
        "",
        "| method | seconds | registered | rotation max (deg) | rotation median (deg) | "
        "translation max (% diag) |",
        "| --- | --- | --- | --- | --- | --- |",
        f"| mvreg register (wall, median of {len(mv['runs'])}: {walls}) | "
        f"{mv['median_wall']:.2f} | {err(first['errors'])} |",
    ]
    if o3 is not None:
        lines.append(
            f"| Open3D multiway (pairwise {o3['pairwise_s']:.1f} + global "
            f"{o3['global_s']:.3f}; {o3['edges']}) | {o3['pairwise_s'] + o3['global_s']:.2f} "
            f"| {err(o3['errors'])} |"
        )
    lines += [
        "",
        f"mvreg's stage times, first run (s): {stages}; peak memory "
        f"{first['peak_rss_mib']:.0f} MiB.",
        "",
    ]
    path = a.out / "large_scans.md"
    path.write_text("\n".join(lines))
    (a.out / "large_scans.json").write_text(
        json.dumps({"mvreg": mv, "open3d": o3}, indent=1, default=float)
    )
    print(f"wrote {path}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3, help="mvreg register runs (median)")
    ap.add_argument("--skip-open3d", action="store_true")
    ap.add_argument("--data", type=Path, default=Path(tempfile.gettempdir()) / "mvreg_large")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks")
    a = ap.parse_args(argv)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    folder = synth_builtin(a.data, VIEWS, POINTS)
    print(f"{folder}: mvreg register x{a.repeats}")
    mv = run_mvreg(folder, a.repeats)
    o3 = None
    if not a.skip_open3d:
        o3 = run_open3d(folder, float(mv["runs"][0]["voxel"]))
    write_report(a, folder, mv, o3)
