"""Runtime of every solver vs the number of patches M (10 .. 1000), on the same instances.

For each M one synthetic instance (data_synth.problems.make_problem(M, d=3, degree=6,
nodes_per_pair=10, noise=0.01, graph="geometric", seed)) is solved by every solver through
``mvreg.solver.solve`` (method "auto": dense up to M d = 900, matrix-free above). Each
(M, solver) case runs in its own subprocess with a time limit, so a slow solver cannot
stall the sweep and the peak memory is per case. Settings: spectral, reg-admm with their
defaults; gpm and balm tol 1e-9 (their output must be accurate enough to be certified, no
Newton polish); c-admm tol 1e-6 (dense only, refused above M d = 1500).

    python scripts/bench_solvers.py             # M in 10, 30, 100, 300, 1000
    python scripts/bench_solvers.py --quick     # M in 10, 30 (smoke test)
    python scripts/bench_solvers.py --out DIR   # write DIR/solvers.{md,png}
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

from bench.common import ROOT, machine_info

SCRIPT = ROOT / "scripts" / "bench_solvers.py"  # its --worker runs one case


SOLVERS = {
    "spectral": {},
    "gpm": dict(tol=1e-9, max_iter=20000),
    "balm": dict(tol=1e-9, max_iter=500),
    "reg-admm": {},
    "c-admm": dict(tol=1e-6, max_iter=3000),
}
PROBLEM = dict(d=3, degree=6, nodes_per_pair=10, noise=0.01, graph="geometric")


def worker(m: int, solver: str, seed: int) -> None:
    import numpy as np

    from data_synth.problems import make_problem
    from mvreg.errors import ConfigError
    from mvreg.metrics import rotation_errors_deg
    from mvreg.solver import solve

    problem, truth = make_problem(m, seed=seed, **PROBLEM)
    t0 = time.perf_counter()
    try:
        res = solve(problem, solver=solver, **SOLVERS[solver])
    except ConfigError as e:
        print(json.dumps({"M": m, "solver": solver, "refused": str(e)}))
        return
    wall = time.perf_counter() - t0
    err = rotation_errors_deg(res.rotations, truth.rotations)
    c = res.certificate
    print(
        json.dumps(
            {
                "M": m,
                "solver": solver,
                "method": res.method,
                "wall_s": wall,
                "timings": res.timings,
                "iterations": res.iterations,
                "converged": bool(res.converged),
                "certified": bool(c.certified),
                "kkt": c.kkt_residual,
                "objective": res.objective,
                "rot_err_median_deg": float(np.median(err)),
                "rot_err_max_deg": float(np.max(err)),
                "rank": res.stats.get("rank"),
                "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20,
            }
        )
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="M in 10, 30 only")
    ap.add_argument("--sizes", type=int, nargs="*", default=[10, 30, 100, 300, 1000])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--timeout", type=float, default=120.0, help="seconds per (M, solver)")
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks"))
    ap.add_argument("--worker", nargs=3, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        worker(int(args.worker[0]), args.worker[1], int(args.worker[2]))
        return 0
    sizes = [10, 30] if args.quick else args.sizes
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    rows = []
    for m in sizes:
        for s in SOLVERS:
            cmd = [
                sys.executable,
                str(SCRIPT),
                "--worker",
                str(m),
                s,
                str(args.seed),
            ]
            env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
            t0 = time.perf_counter()
            try:
                p = subprocess.run(
                    cmd, capture_output=True, text=True, timeout=args.timeout, cwd=ROOT, env=env
                )
                if p.returncode != 0:
                    last = (p.stderr.strip().splitlines() or ["?"])[-1]
                    r = {"M": m, "solver": s, "failed": last[:160]}
                else:
                    r = json.loads(p.stdout.strip().splitlines()[-1])
            except subprocess.TimeoutExpired:
                r = {"M": m, "solver": s, "timeout": args.timeout}
            rows.append(r)
            status = (
                f"{r['wall_s']:.2f} s, certified {r['certified']}"
                if "wall_s" in r
                else next(v for k, v in r.items() if k in ("refused", "failed", "timeout"))
            )
            print(
                f"M={m} {s}: {status} ({time.perf_counter() - t0:.1f} s with startup)", flush=True
            )

    # ------------------------------------------------------------------ plot
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for i, s in enumerate(SOLVERS):
        pts = [r for r in rows if r["solver"] == s and "wall_s" in r]
        if not pts:
            continue
        color = f"C{i}"
        ax.loglog([r["M"] for r in pts], [r["wall_s"] for r in pts], "-", color=color, label=s)
        for r in pts:
            ax.loglog(
                r["M"],
                r["wall_s"],
                "o",
                color=color,
                markerfacecolor=color if r["certified"] else "none",
            )
        for r in rows:
            if r["solver"] == s and "timeout" in r:
                ax.loglog(r["M"], r["timeout"], "x", color=color, ms=9)
    ax.set_xlabel("patches M (d = 3)")
    ax.set_ylabel("solve() wall time (s)")
    ax.set_title("All solvers on the same instances (filled: certified; x: time limit)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    png = out / "solvers.png"
    fig.savefig(png, dpi=110)
    plt.close(fig)

    # ------------------------------------------------------------------ markdown
    lines = ["# Runtime of every solver vs M (same instances)", ""]
    lines += machine_info(
        "in every worker (and solve() pins BLAS to 1 thread); the machine's 2 cores are shared "
        "with other jobs, so times are indicative"
    )
    lines += [
        "- total wall time: TOTAL_WALL",
        "",
        f"Instances: `make_problem(M, seed={args.seed}, "
        + ", ".join(f"{k}={v!r}" for k, v in PROBLEM.items())
        + ")`, one per M, the same for every solver. Settings: "
        + "; ".join(f"{s} {kw or '(defaults)'}" for s, kw in SOLVERS.items())
        + f". Time limit {args.timeout:g} s per case. Time = solve() wall time (spectrum, "
        "iterations, certificate, translations; problem generation excluded); peak memory = "
        "peak RSS of the worker process.",
        "",
        f"![time vs M]({png.name})",
        "",
        "## Wall time (s) per solver",
        "",
        "| M | " + " | ".join(SOLVERS) + " |",
        "| --- | " + " | ".join("---" for _ in SOLVERS) + " |",
    ]
    for m in sizes:
        cells = []
        for s in SOLVERS:
            r = next(r for r in rows if r["M"] == m and r["solver"] == s)
            if "wall_s" in r:
                cells.append(f"{r['wall_s']:.3g}" + ("" if r["certified"] else " (not certified)"))
            elif "refused" in r:
                cells.append("refused (size limit)")
            elif "timeout" in r:
                cells.append(f"> {r['timeout']:g} (time limit)")
            else:
                cells.append("failed")
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "## Details",
        "",
        "| M | solver | method | wall s | iterations | converged | certified | KKT residual | "
        "REG cost | rot err median / max (deg) | c-admm rank | peak GiB |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        if "wall_s" not in r:
            why = r.get("refused") or r.get("failed") or f"time limit {r.get('timeout')} s"
            lines.append(f"| {r['M']} | {r['solver']} | {why} |  |  |  |  |  |  |  |  |  |")
            continue
        lines.append(
            f"| {r['M']} | {r['solver']} | {r['method']} | {r['wall_s']:.3f} | {r['iterations']} "
            f"| {'yes' if r['converged'] else 'no'} | {'yes' if r['certified'] else 'NO'} | "
            f"{r['kkt']:.1e} | {r['objective']:.6g} | {r['rot_err_median_deg']:.3f} / "
            f"{r['rot_err_max_deg']:.3f} | {r['rank'] if r['rank'] is not None else ''} | "
            f"{r['peak_rss_gib']:.2f} |"
        )
    lines += ["", "Observations (computed from the tables):", ""]
    ok = [r for r in rows if "wall_s" in r]
    for m in sizes:
        here = [r for r in ok if r["M"] == m]
        if not here:
            continue
        fastest = min(here, key=lambda r: r["wall_s"])
        cert = [r for r in here if r["certified"]]
        fastest_cert = min(cert, key=lambda r: r["wall_s"]) if cert else None
        objs = [r["objective"] for r in cert]
        agree = (max(objs) - min(objs)) / max(min(objs), 1e-300) if len(objs) > 1 else 0.0
        lines.append(
            f"- M = {m}: fastest {fastest['solver']} ({fastest['wall_s']:.3g} s"
            + ("" if fastest["certified"] else ", not certified")
            + ")"
            + (
                f"; fastest certified {fastest_cert['solver']} ({fastest_cert['wall_s']:.3g} s)"
                if fastest_cert
                else "; nothing certified"
            )
            + f"; certified: {', '.join(r['solver'] for r in cert) or 'none'}"
            + (f" (their REG costs agree to {agree:.1e} relative)" if len(cert) > 1 else "")
            + "."
        )
    zero = sorted({r["M"] for r in ok if r["solver"] == "reg-admm" and r["iterations"] == 0})
    if zero:
        lines.append(
            "- reg-admm made 0 ADMM iterations at M = "
            + ", ".join(map(str, zero))
            + ": its checkpoint 0 (the spectral estimate, Newton-polished) was already "
            "certified, so its time is spectrum + Newton polish + certificate."
        )
    for s in SOLVERS:
        pts = sorted((r["M"], r["wall_s"]) for r in ok if r["solver"] == s)
        if len(pts) >= 2 and pts[-1][0] > pts[0][0]:
            import math

            slope = math.log(pts[-1][1] / pts[0][1]) / math.log(pts[-1][0] / pts[0][0])
            lines.append(
                f"- {s}: from M = {pts[0][0]} to M = {pts[-1][0]} the time grows like "
                f"M^{slope:.2f} (end points)."
            )
    lines += [""]
    md = out / "solvers.md"
    md.write_text("\n".join(lines).replace("TOTAL_WALL", f"{time.perf_counter() - t_start:.1f} s"))
    print(f"wrote {md} and {png} in {time.perf_counter() - t_start:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
