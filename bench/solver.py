"""Benchmark of the global solver (issue 2): dense vs matrix-free REG-ADMM vs M.

Each case runs in its own subprocess (own peak memory, own time limit): generate a
synthetic patch problem (d = 3, each patch overlapping ~6 others, 20 shared nodes per
overlapping pair, noise 1% of the patch size), then time ``mvreg.solver.solve`` split into
building C, initialisation (spectrum + spectral estimate), iterations (REG-ADMM and Newton
polish) and certificate. Writes docs/benchmarks/solver.md and solver.png.

    python scripts/bench_solver.py                 # full sweep (M up to 100,000)
    python scripts/bench_solver.py --quick         # M in {10, 100, 1000}
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.common import ROOT, machine

SCRIPT = ROOT / "scripts" / "bench_solver.py"  # its --worker runs one case

DENSE_LIMIT_GIB = 8.0


def worker(m: int, method: str, seed: int, save: str) -> None:
    import numpy as np

    from data_synth.problems import make_problem
    from mvreg.metrics import rotation_errors_deg
    from mvreg.solver import solve

    problem, truth = make_problem(m, d=3, degree=6, nodes_per_pair=20, noise=0.01, seed=seed)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    res = solve(problem, method=method)
    wall = time.perf_counter() - t0
    err = rotation_errors_deg(res.rotations, truth.rotations)
    np.save(save, res.rotations)
    c = res.certificate
    print(
        json.dumps(
            {
                "M": m,
                "method": res.method,
                "wall_s": wall,
                "timings": res.timings,
                "iterations": res.iterations,
                "newton_steps": res.stats.get("newton_steps"),
                "stopped_by": res.stats.get("stopped_by"),
                "certified": bool(c.certified),
                "min_eigenvalue": c.min_eigenvalue,
                "kkt": c.kkt_residual,
                "rot_err_median_deg": float(np.median(err)),
                "rot_err_max_deg": float(np.max(err)),
                "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
                "rss_before_solve_gib": rss0 / 2**20,
                "observations": problem.num_observations,
                "blas_threads": res.stats.get("blas_threads"),
            }
        )
    )


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--sizes", type=int, nargs="*", default=[10, 100, 1000, 3000, 10000, 30000, 100000]
    )
    ap.add_argument("--quick", action="store_true", help="M in {10, 100, 1000} only")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--timeout", type=float, default=1200.0, help="seconds per case")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks")
    ap.add_argument(
        "--cli-sizes",
        type=int,
        nargs="*",
        default=[10000, 100000],
        help="also time the whole `mvreg solve` command (load, solve, certify, write) at these M",
    )
    ap.add_argument("--worker", nargs=4, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.worker:
        worker(int(a.worker[0]), a.worker[1], int(a.worker[2]), a.worker[3])
        return
    sizes = [10, 100, 1000] if a.quick else a.sizes
    rows = []
    tmp = Path(tempfile.mkdtemp())
    for m in sizes:
        for method in ("dense", "matrix-free"):
            n = 3 * m
            need = 4 * n * n * 8 / 2**30  # C, A and eigensolver workspaces
            if method == "dense" and need > DENSE_LIMIT_GIB:
                rows.append(
                    {
                        "M": m,
                        "method": "dense",
                        "skipped": f"needs ~{need:.0f} GiB > {DENSE_LIMIT_GIB:.0f} GiB",
                    }
                )
                continue
            save = str(tmp / f"{m}_{method}.npy")
            cmd = [sys.executable, str(SCRIPT), "--worker", str(m), method, str(a.seed), save]
            print(f"M={m} {method} ...", file=sys.stderr, flush=True)
            try:
                p = subprocess.run(
                    cmd,
                    capture_output=True,
                    text=True,
                    timeout=a.timeout,
                    cwd=ROOT,
                    env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
                )
                if p.returncode != 0:
                    rows.append(
                        {
                            "M": m,
                            "method": method,
                            "skipped": "failed: " + p.stderr.strip().splitlines()[-1][:120],
                        }
                    )
                    continue
                r = json.loads(p.stdout.strip().splitlines()[-1])
                r["save"] = save
                rows.append(r)
                print(
                    f"   {r['wall_s']:.2f} s certified={r['certified']} peak {r['peak_rss_gib']:.2f} GiB",
                    file=sys.stderr,
                )
            except subprocess.TimeoutExpired:
                rows.append(
                    {"M": m, "method": method, "skipped": f"timed out after {a.timeout:.0f} s"}
                )
    # Agreement of dense and matrix-free where both ran.
    import numpy as np

    from mvreg.geometry import rotation_angle_deg

    agree = {}
    for m in sizes:
        got = {r["method"]: r for r in rows if r["M"] == m and "save" in r}
        if len(got) == 2:
            a_, b_ = np.load(got["dense"]["save"]), np.load(got["matrix-free"]["save"])
            agree[m] = float(rotation_angle_deg(np.einsum("mji,mjk->mik", a_, b_)).max())
    cli = [] if a.quick else [time_command(m, a, tmp) for m in a.cli_sizes]
    write_report(a, rows, agree, cli)


def time_command(m: int, a, tmp: Path) -> dict:
    """Wall time and peak RSS of the whole `mvreg solve` on a problem file (GNU time -v)."""
    exe = str(Path(sys.executable).with_name("mvreg"))
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    prob, res = tmp / f"p{m}.npz", tmp / f"r{m}.json"
    subprocess.run(
        [exe, "make-problem", "--patches", str(m), "--seed", str(a.seed), "--out", str(prob)],
        check=True,
        capture_output=True,
        env=env,
    )
    print(f"mvreg solve M={m} ...", file=sys.stderr, flush=True)
    try:
        p = subprocess.run(
            ["/usr/bin/time", "-v", exe, "solve", str(prob), "--out", str(res)],
            capture_output=True,
            text=True,
            timeout=a.timeout,
            env=env,
        )
    except subprocess.TimeoutExpired:
        return {"M": m, "skipped": f"timed out after {a.timeout:.0f} s"}
    info = {}
    for line in p.stderr.splitlines():
        k, _, v = line.strip().rpartition(": ")
        info[k] = v
    wall = info.get("Elapsed (wall clock) time (h:mm:ss or m:ss)", "nan")
    parts = [float(x) for x in wall.split(":")]
    secs = sum(x * 60**i for i, x in enumerate(reversed(parts)))
    out = {
        "M": m,
        "wall_s": secs,
        "peak_gib": float(info.get("Maximum resident set size (kbytes)", "nan")) / 2**20,
        "summary": p.stdout.strip().splitlines()[-1] if p.stdout.strip() else p.stderr[-200:],
        "returncode": p.returncode,
    }
    if p.returncode == 0:
        r = json.loads(res.read_text())
        out["certified"] = r["certificate"]["certified"]
        out["timings"] = r["solver"]["timings_s"]
    print(f"   {out}", file=sys.stderr)
    return out


def write_report(a, rows, agree, cli) -> None:
    from mvreg.solver import pardiso

    a.out.mkdir(parents=True, exist_ok=True)
    cmd = "python scripts/bench_solver.py " + " ".join(sys.argv[1:])
    lines = [
        "# Global solver: dense vs matrix-free REG-ADMM",
        "",
        f"- Command: `{cmd}` ({datetime.date.today().isoformat()})",
        f"- Machine: {machine()}",
        "- BLAS threads: 1 (`OPENBLAS_NUM_THREADS=1`, and `solve()` limits BLAS to 1 thread)",
        "- Sparse factorizations: "
        + (
            "Intel MKL PARDISO (`mvreg/solver/pardiso.py`)"
            if pardiso.available()
            else "SciPy SuperLU, nested-dissection order (MKL PARDISO not available)"
        ),
        "- Problems: `data_synth.problems.make_problem(M, d=3, degree=6, nodes_per_pair=20, "
        f"noise=0.01, graph='geometric', seed={a.seed})`: patches in space joined to their nearest "
        "neighbours (mean degree ~6), 20 shared nodes per overlapping pair, Gaussian noise of 1% of the "
        "patch size.",
        "- Time = `solve()` wall time: build C + init (spectrum, spectral estimate) + iterations "
        "(REG-ADMM and Newton polish) + certificate (+ translations). Problem generation excluded. "
        "Peak memory = peak RSS of the worker process (includes the problem itself).",
        "",
        "| M | method | total s | build C | init | iterate+polish | certificate | ADMM iters | Newton | certified | min eig (rel) | rot err median / max (deg) | peak GiB |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "skipped" in r:
            lines.append(
                f"| {r['M']} | {r['method']} | {r['skipped']} |  |  |  |  |  |  |  |  |  |  |"
            )
            continue
        t = r["timings"]
        lines.append(
            f"| {r['M']} | {r['method']} | {r['wall_s']:.2f} | {t['build_C']:.2f} | {t['init']:.2f} | "
            f"{t['iterations'] + t['polish']:.2f} | {t['certificate']:.2f} | {r['iterations']} | "
            f"{r['newton_steps']} | {'yes' if r['certified'] else 'NO'} | {r['min_eigenvalue']:.2e} | "
            f"{r['rot_err_median_deg']:.3f} / {r['rot_err_max_deg']:.3f} | {r['peak_rss_gib']:.2f} |"
        )
    lines += [
        "",
        "Dense vs matrix-free rotations (max angle between the two solutions, degrees): "
        + (", ".join(f"M={m}: {v:.1e}" for m, v in agree.items()) or "n/a"),
        "",
    ]
    if cli:
        lines += [
            "## The whole command against the targets",
            "",
            "`mvreg make-problem --patches M --out pM.npz` (same generator and seed), then "
            "`/usr/bin/time -v mvreg solve pM.npz --out rM.json`: Python start-up, imports, "
            "loading and validating the file, solving, certifying and writing the JSON.",
            "",
            "| M | wall s | peak GiB | certified | target | met | solve() stages (s) |",
            "|---|---|---|---|---|---|---|",
        ]
        targets = {10000: (15.0, None), 100000: (240.0, 8.0)}
        for c in cli:
            t_s, t_m = targets.get(c["M"], (None, None))
            tgt = (f"<= {t_s:.0f} s" if t_s else "") + (f", <= {t_m:.0f} GiB" if t_m else "")
            if "skipped" in c or c.get("returncode"):
                lines.append(f"| {c['M']} | {c.get('skipped', 'failed')} |  |  | {tgt} | no |  |")
                continue
            met = (t_s is None or c["wall_s"] <= t_s) and (t_m is None or c["peak_gib"] <= t_m)
            met = met and c.get("certified", False)
            st = ", ".join(f"{k} {v:.1f}" for k, v in c.get("timings", {}).items())
            lines.append(
                f"| {c['M']} | {c['wall_s']:.1f} | {c['peak_gib']:.2f} | "
                f"{'yes' if c.get('certified') else 'NO'} | {tgt} | {'yes' if met else 'NO'} | {st} |"
            )
        lines.append("")
    (a.out / "solver.md").write_text("\n".join(lines) + "\n")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 4))
        for method in ("dense", "matrix-free"):
            pts = [(r["M"], r["wall_s"]) for r in rows if r["method"] == method and "wall_s" in r]
            if pts:
                ax.loglog(*zip(*pts, strict=True), "o-", label=method)
        ax.set_xlabel("patches M")
        ax.set_ylabel("solve time (s)")
        ax.set_title("REG-ADMM + certificate, d=3, 1% noise")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
        fig.tight_layout()
        fig.savefig(a.out / "solver.png", dpi=120)
    except ImportError:
        print("matplotlib missing: no plot (pip install '.[bench]')", file=sys.stderr)
    print((a.out / "solver.md").read_text())


if __name__ == "__main__":
    main()
