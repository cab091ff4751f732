"""Synthetic patch problems: mvreg's matrix-free REG-ADMM vs GTSAM fed Kabsch edges.

Each (M, method) case runs in a subprocess (``scripts/bench_peers.py --patch-worker M
method seed``) with a time limit; :func:`patch_worker` prints one JSON row.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np

from bench.common import ROOT
from bench.peers.gtsam import gtsam_solve
from bench.peers.settings import PATCH

SCRIPT = ROOT / "scripts" / "bench_peers.py"  # its --patch-worker runs one case


def kabsch_edges(problem, edges):
    """T_i_j (j's coordinates into i's) per edge from the nodes both patches see."""
    from mvreg.geometry import project_to_orthogonal

    coords, patch, node = problem.coords, problem.patch, problem.node
    order = np.lexsort((node, patch))
    key = patch[order].astype(np.int64) * (int(node.max()) + 1) + node[order]
    look = dict(zip(key.tolist(), order.tolist(), strict=True))
    nmax = int(node.max()) + 1
    # Nodes per patch.
    by_patch: dict[int, np.ndarray] = {}
    srt = np.argsort(patch, kind="stable")
    bounds = np.searchsorted(patch[srt], np.arange(problem.num_patches + 1))
    for m in range(problem.num_patches):
        by_patch[m] = node[srt[bounds[m] : bounds[m + 1]]]
    rel, cov = {}, {}
    for i, j in edges:
        shared = np.intersect1d(by_patch[i], by_patch[j])
        a = coords[[look[i * nmax + s] for s in shared]]
        b = coords[[look[j * nmax + s] for s in shared]]
        ca, cb = a.mean(0), b.mean(0)
        R = project_to_orthogonal(((a - ca).T @ (b - cb))[None])[0]
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = ca - R @ cb
        rel[(int(i), int(j))] = T
        # Covariance of the estimate from the fit residual: rotation from the spread of the
        # centred points, centroid s^2 / n; moved from the centroid to the frame origin
        # (v = dc + [cb]x omega) in GTSAM's tangent (omega, v).
        k = len(shared)
        res = a - (b @ R.T + T[:3, 3])
        s2 = float(np.sum(res**2)) / max(3 * k - 6, 1)
        q = b - cb
        H = np.sum(q * q) * np.eye(3) - q.T @ q
        c_om = s2 * np.linalg.inv(H)
        cx = np.array([[0, -cb[2], cb[1]], [cb[2], 0, -cb[0]], [-cb[1], cb[0], 0]])
        A = np.block([[np.eye(3), np.zeros((3, 3))], [cx, np.eye(3)]])
        C = np.block([[c_om, np.zeros((3, 3))], [np.zeros((3, 3)), s2 / k * np.eye(3)]])
        cov[(int(i), int(j))] = A @ C @ A.T
    return rel, cov


def patch_worker(m: int, method: str, seed: int) -> None:
    from data_synth.problems import make_problem
    from mvreg.metrics import rotation_errors_deg, translation_errors

    problem, truth = make_problem(m, seed=seed, **PATCH)
    out = {"M": m, "method": method, "edges": int(len(truth.edges))}
    if method == "mvreg":
        from mvreg.solver import solve

        t0 = time.perf_counter()
        res = solve(problem, method="matrix-free")
        out["global_s"] = time.perf_counter() - t0
        out["pairwise_s"] = 0.0
        R, t = res.rotations, res.translations
        R_rot_only = R
        out["certified"] = bool(res.certificate.certified)
        out["rotation_s"] = out["global_s"] - res.timings.get("translations", 0.0)
    else:
        t0 = time.perf_counter()
        rel, cov = kabsch_edges(problem, truth.edges)
        out["pairwise_s"] = time.perf_counter() - t0
        g = gtsam_solve(m, rel, cov)
        out["global_s"] = g["rotation_s"] + g["translation_s"]
        out["rotation_s"] = g["rotation_s"]
        keep = sorted(g["T"])
        if len(keep) != m:
            out["failed"] = f"only {len(keep)} of {m} patches connected"
        R = np.stack([g["T"][k][:3, :3] for k in keep])
        t = np.stack([g["T"][k][:3, 3] for k in keep])
        R_rot_only = np.stack([g["R_shonan"][k] for k in keep])
        out["certified"] = g["certified"]
        out["min_eig"] = g["min_eig"]
    er = rotation_errors_deg(R, truth.rotations)
    er0 = rotation_errors_deg(R_rot_only, truth.rotations)
    et = translation_errors(R, t, truth.rotations, truth.translations)
    out |= {
        "rot_med": float(np.median(er)),
        "rot_max": float(np.max(er)),
        "rot_max_rotation_stage": float(np.max(er0)),
        "tr_med": float(np.median(et)),
        "tr_max": float(np.max(et)),
    }
    print(json.dumps(out))


def run_patches(sizes, seed, timeout, log=print) -> list[dict]:
    rows = []
    for m in sizes:
        for method in ("mvreg", "gtsam"):
            cmd = [sys.executable, str(SCRIPT), "--patch-worker", str(m), method, str(seed)]
            log(f"patch M={m} {method} ...")
            try:
                p = subprocess.run(
                    cmd,
                    capture_output=True,
                    text=True,
                    timeout=timeout,
                    cwd=ROOT,
                    env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
                )
                if p.returncode != 0:
                    tail = (p.stderr.strip().splitlines() or ["?"])[-1][:160]
                    rows.append({"M": m, "method": method, "failed": tail})
                else:
                    rows.append(json.loads(p.stdout.strip().splitlines()[-1]))
            except subprocess.TimeoutExpired:
                rows.append(
                    {"M": m, "method": method, "failed": f"timed out after {timeout:.0f} s"}
                )
            r = rows[-1]
            log(
                f"   {r.get('failed', '')} {r.get('pairwise_s', 0):.2f}+{r.get('global_s', 0):.2f} s"
                f" rot max {r.get('rot_max', float('nan')):.3f}"
            )
    return rows


# ----------------------------------------------------------------------------- report
