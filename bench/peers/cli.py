"""The command line of the peer benchmark (``scripts/bench_peers.py``)."""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import bench.peers
from bench.common import ROOT, SHARED
from bench.peers.datasets import run_bunny, run_synth
from bench.peers.gtsam import gtsam_solve
from bench.peers.open3d import run_open3d_fed, run_open3d_own
from bench.peers.patches import patch_worker, run_patches
from bench.peers.report import write_report
from bench.peers.settings import CONDITIONS


def warm_up() -> None:
    """Load every library and first-call cache before anything is timed."""
    from data_synth import synthesize_scans
    from mvreg.pipeline import register

    with tempfile.TemporaryDirectory() as tmp:
        s = synthesize_scans(
            "builtin", Path(tmp) / "w", views=4, points_per_scan=3000, seed=0, random_frames=True
        )
        reg = register(Path(tmp) / "w", truth=s.T_world_scan)
        names = list(s.T_world_scan)
        pts = [x.points for x in reg.scans]
        o3 = run_open3d_own(pts, reg.voxel_size, 0)
        rel = {
            (i, j): np.linalg.inv(s.T_world_scan[names[i]]) @ s.T_world_scan[names[j]]
            for i in range(len(names))
            for j in range(i + 1, len(names))
        }
        fed = run_open3d_fed(len(names), rel, o3["prep"], reg.voxel_size, 0.0)
        gtsam_solve(len(names), rel, fed["cov"])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(
        description=bench.peers.__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--quick", action="store_true", help="bunny + one mesh/condition, M <= 1000")
    ap.add_argument("--seeds", type=int, default=1, help="seeds per synthetic mesh/condition")
    ap.add_argument("--seed", type=int, default=0, help="seed of the patch problems")
    ap.add_argument("--sizes", type=int, nargs="*", default=[100, 1000, 3000, 10000])
    ap.add_argument("--meshes", nargs="*", help="mesh stems (default: all)")
    ap.add_argument("--conditions", nargs="*", choices=list(CONDITIONS), default=list(CONDITIONS))
    ap.add_argument("--skip", nargs="*", default=[], choices=["bunny", "synthetic", "patches"])
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds per patch case")
    ap.add_argument(
        "--all-solvers",
        action="store_true",
        help="the other mvreg global solvers on every synthetic set (default: clean, seed 0)",
    )
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks")
    ap.add_argument("--patch-worker", nargs=3, help=argparse.SUPPRESS)
    ap.add_argument(
        "--checkpoint",
        type=Path,
        default=Path(tempfile.gettempdir()) / "bench_peers_checkpoint.json",
        help="rows written here after each dataset",
    )
    ap.add_argument("--resume", action="store_true", help="skip datasets in the checkpoint")
    ap.add_argument(
        "--report-from",
        type=Path,
        help="rewrite the report from an earlier run's peers.json (same numbers, no re-run)",
    )
    a = ap.parse_args(argv)
    if a.report_from:
        d = json.loads(a.report_from.read_text())
        for k in ("quick", "all_solvers"):
            setattr(a, k, d["args"].get(k) == "True")
        a.seeds, a.seed, a.timeout = (
            int(d["args"]["seeds"]),
            int(d["args"]["seed"]),
            float(d["args"]["timeout"]),
        )
        write_report(
            a, d["bunny"], d["synthetic"], d["patches"], d["wall_s"], d["command"], d["date"]
        )
        return
    if a.patch_worker:
        patch_worker(int(a.patch_worker[0]), a.patch_worker[1], int(a.patch_worker[2]))
        return
    cmd = "OPENBLAS_NUM_THREADS=1 python scripts/bench_peers.py " + " ".join(
        sys.argv[1:] if argv is None else argv
    )
    t_start = time.perf_counter()
    log = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    meshes = sorted((SHARED / "meshes").glob("*.obj"))
    if a.meshes:
        meshes = [m for m in meshes if m.stem in a.meshes]
    sizes = a.sizes
    conds = a.conditions
    if a.quick:
        meshes, sizes, conds, a.seeds = meshes[:1], [s for s in sizes if s <= 1000], conds[:1], 1
    bunny, synth, patches = [], [], []
    done_before = 0.0
    if a.resume and a.checkpoint.exists():  # continue an interrupted run
        ck = json.loads(a.checkpoint.read_text())
        bunny, synth, done_before = ck["bunny"], ck["synthetic"], ck["elapsed_s"]
        cmd = ck["command"] + " (resumed with --resume)"
        log(f"resuming: {len(bunny)} bunny rows, {len(synth)} synthetic rows")

    def checkpoint():
        a.checkpoint.write_text(
            json.dumps(
                {
                    "command": cmd,
                    "elapsed_s": done_before + time.perf_counter() - t_start,
                    "bunny": bunny,
                    "synthetic": synth,
                },
                default=str,
            )
        )

    log("warm-up (untimed) ...")
    warm_up()
    if "bunny" not in a.skip and not bunny:
        log("bunny ...")
        bunny = run_bunny(0, log)
        checkpoint()
    if "synthetic" not in a.skip:
        if not meshes:
            sys.exit(
                f"no meshes in {SHARED / 'meshes'} (../shared/data must be beside the project)"
            )
        done = {(r["mesh"], r["condition"], r["seed"]) for r in synth}
        with tempfile.TemporaryDirectory() as tmp:
            for mesh in meshes:
                for cond in conds:
                    for seed in range(a.seeds):
                        if (mesh.stem, cond, seed) in done:
                            continue
                        log(f"{mesh.stem} / {cond} / seed {seed} ...")
                        solvers = a.all_solvers or (cond == "clean" and seed == 0)
                        try:
                            synth += run_synth(mesh, cond, seed, Path(tmp), log, solvers)
                        except Exception as e:  # keep going; the report lists the failure
                            log(f"  failed: {type(e).__name__}: {e}")
                            synth.append(
                                {
                                    "dataset": f"{mesh.stem} / {cond} / seed {seed}",
                                    "method": "mvreg",
                                    "mesh": mesh.stem,
                                    "condition": cond,
                                    "seed": seed,
                                    "failed": f"benchmark error {type(e).__name__}: {e}"[:200],
                                }
                            )
                        checkpoint()
    if "patches" not in a.skip:
        patches = run_patches(sizes, a.seed, a.timeout, log)
    write_report(a, bunny, synth, patches, done_before + time.perf_counter() - t_start, cmd)
