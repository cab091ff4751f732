"""Paper 000 (Singh & Chaudhury), Fig. 3: rank of the C-SDP optimum vs noise (phase transition).

C-SDP (REG-SDP without the rank constraint) is solved by c-admm (mvreg/solver/c_admm.py) to
a tight tolerance; the rank of its optimum is the number of eigenvalues above 1e-3 times the
largest one. Below a noise threshold the rank is d (the relaxation is tight), above it the
rank exceeds d. Three setups, at least 20 random instances (seeds) per noise level:

  A. the network of the paper's Fig. 2: d = 2, 10 nodes in the unit square, 3 patches each
     holding all nodes (noise level = variance of the Gaussian noise, as in the paper);
  B. d = 2, 20 patches on a geometric overlap graph (data_synth.problems.make_problem,
     mean degree 4, 6 shared nodes per overlapping pair; noise level = standard deviation
     relative to the patch size ~1);
  C. the same with d = 3.

    python scripts/paper000_fig3.py               # full (20 seeds per level)
    python scripts/paper000_fig3.py --quick       # 3 seeds, 3 levels per setup
    python scripts/paper000_fig3.py --out DIR     # write DIR/paper000_fig3.{md,png}
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from bench.common import ROOT, blas_threads, machine_info
from data_synth.problems import make_problem
from mvreg.geometry import random_rotations
from mvreg.solver import PatchProblem, RegOperator
from mvreg.solver.c_admm import RANK_RTOL, c_admm
from mvreg.solver.spectral import spectral_rotations, spectrum


def paper_network(var: float, seed: int) -> PatchProblem:
    """Setup A (as in scripts/paper000_fig2.py)."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.0, 1.0, size=(10, 2))
    rot = random_rotations(rng, 3, 2)
    coords, patch, node = [], [], []
    for i in range(3):
        x = z @ rot[i]
        if var > 0:
            x = x + math.sqrt(var) * rng.standard_normal(x.shape)
        coords.append(x)
        patch += [i] * 10
        node += list(range(10))
    return PatchProblem(np.vstack(coords), np.array(patch), np.array(node))


SETUPS = {
    "A": dict(
        title="A: paper's network (d = 2, 10 nodes, 3 patches)",
        d=2,
        levels=[0.0, 0.001, 0.01, 0.03, 0.1, 0.3, 1.0, 3.0],
        quick=[0.0, 0.1, 1.0],
        level_name="noise variance",
        make=lambda lvl, seed: paper_network(lvl, seed),
    ),
    "B": dict(
        title="B: d = 2, 20 patches, geometric overlap graph",
        d=2,
        levels=[0.0, 0.05, 0.1, 0.15, 0.2, 0.3, 0.5, 1.0],
        quick=[0.0, 0.2, 1.0],
        level_name="noise std / patch size",
        make=lambda lvl, seed: make_problem(
            20, d=2, degree=4, nodes_per_pair=6, noise=lvl, seed=seed
        )[0],
    ),
    "C": dict(
        title="C: d = 3, 20 patches, geometric overlap graph",
        d=3,
        levels=[0.0, 0.05, 0.1, 0.15, 0.2, 0.3, 0.5, 1.0],
        quick=[0.0, 0.2, 1.0],
        level_name="noise std / patch size",
        make=lambda lvl, seed: make_problem(
            20, d=3, degree=4, nodes_per_pair=6, noise=lvl, seed=seed
        )[0],
    ),
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="3 seeds and 3 levels per setup")
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks"))
    ap.add_argument("--seeds", type=int, default=None, help="instances per level (20)")
    ap.add_argument("--tol", type=float, default=1e-8, help="c-admm tolerance")
    ap.add_argument("--max-iter", type=int, default=None)
    args = ap.parse_args(argv)
    seeds = args.seeds or (3 if args.quick else 20)
    max_iter = args.max_iter or (2000 if args.quick else 20000)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()

    results = {}
    for key, st in SETUPS.items():
        d = st["d"]
        rows = []
        for lvl in st["quick"] if args.quick else st["levels"]:
            ranks, ev_next, its, conv, times, gaps = [], [], [], [], [], []
            for seed in range(seeds):
                problem = st["make"](lvl, seed)
                op = RegOperator(problem)
                spec = spectrum(op, dense=True)
                t0 = time.perf_counter()
                res = c_admm(
                    op.dense(),
                    d,
                    spectral_rotations(spec, d),
                    lam_d1=float(spec.smallest[d]),
                    lam_max=float(spec.largest),
                    tol=args.tol,
                    max_iter=max_iter,
                )
                times.append(time.perf_counter() - t0)
                ranks.append(res.rank)
                ev_next.append(float(res.eigenvalues[d] / res.eigenvalues[0]))
                its.append(res.iterations)
                conv.append(res.converged)
                # relative to the optimum, or to lambda_max(C) Md when the optimum is ~0
                scale = max(abs(res.upper), 1e-12 * float(spec.largest) * op.n)
                gaps.append((res.upper - res.lower) / scale)
            ranks = np.array(ranks)
            rows.append(
                dict(
                    level=lvl,
                    mean_rank=float(ranks.mean()),
                    tight=float(np.mean(ranks == d)),
                    min_rank=int(ranks.min()),
                    max_rank=int(ranks.max()),
                    ev_next=float(np.median(ev_next)),
                    its=float(np.mean(its)),
                    conv=float(np.mean(conv)),
                    gap=float(np.max(gaps)),
                    time=float(np.mean(times)),
                )
            )
            print(key, rows[-1], flush=True)
        results[key] = rows

    # ------------------------------------------------------------------ plot
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(SETUPS), figsize=(5 * len(SETUPS), 4))
    for ax, (key, st) in zip(axes, SETUPS.items(), strict=True):
        rows = results[key]
        x = np.array([r["level"] for r in rows])
        xp = np.where(x > 0, x, x[x > 0].min() / 3 if np.any(x > 0) else 1.0)
        ax.semilogx(xp, [r["mean_rank"] for r in rows], "o-", label="mean rank of G*")
        ax.fill_between(
            xp,
            [r["min_rank"] for r in rows],
            [r["max_rank"] for r in rows],
            alpha=0.2,
            label="min .. max",
        )
        ax.axhline(st["d"], color="k", ls=":", lw=1, label=f"d = {st['d']}")
        ax2 = ax.twinx()
        ax2.semilogx(xp, [r["tight"] for r in rows], "s--", color="tab:red", alpha=0.7)
        ax2.set_ylim(-0.05, 1.05)
        ax2.set_ylabel("fraction tight (rank = d)", color="tab:red")
        ax.set_xlabel(st["level_name"] + " (0 plotted at the left end)")
        ax.set_ylabel("rank of the C-SDP optimum")
        ax.set_title(st["title"], fontsize=9)
        ax.legend(fontsize=8, loc="center left")
    fig.suptitle(f"Paper 000 Fig. 3 reproduced: C-SDP rank vs noise ({seeds} seeds per level)")
    fig.tight_layout()
    png = out / "paper000_fig3.png"
    fig.savefig(png, dpi=110)
    plt.close(fig)

    # ------------------------------------------------------------------ markdown
    lines = ["# Paper 000 Fig. 3: rank of the C-SDP optimum vs noise", ""]
    lines += machine_info(
        f"(threadpoolctl: {blas_threads()}); the machine's 2 cores are shared with other jobs"
    )
    lines += [
        "- total wall time: TOTAL_WALL",
        "",
        f"C-SDP solved by c-admm (rho auto, start: spectral estimate, tol {args.tol:g}, at "
        f"most {max_iter} iterations); rank = number of eigenvalues of the (feasible) "
        f"optimum above {RANK_RTOL:g} x the largest; {seeds} instances (seeds 0..{seeds - 1}) "
        "per noise level.",
        "",
        f"![rank vs noise]({png.name})",
        "",
    ]
    for key, st in SETUPS.items():
        rows = results[key]
        d = st["d"]
        lines += [
            f"## {st['title']}",
            "",
            f"| {st['level_name']} | mean rank | fraction tight (rank = d) | min rank | max rank "
            "| median lambda_{d+1}(G*) / lambda_1(G*) | c-admm iterations (mean) | "
            "converged | max relative duality gap | time per solve (s) |",
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
        ]
        for r in rows:
            lines.append(
                f"| {r['level']:g} | {r['mean_rank']:.2f} | {r['tight']:.2f} | {r['min_rank']} "
                f"| {r['max_rank']} | {r['ev_next']:.2e} | {r['its']:.0f} | {r['conv']:.2f} | "
                f"{r['gap']:.1e} | {r['time']:.3f} |"
            )
        lines += [""]
        tight_levels = [r["level"] for r in rows if r["tight"] == 1.0]
        loose_levels = [r["level"] for r in rows if r["tight"] < 1.0]
        all_loose = [r["level"] for r in rows if r["tight"] == 0.0]
        first_loose = min(loose_levels) if loose_levels else None
        obs = ["Observations (computed from the table):", ""]
        if first_loose is None:
            obs.append(f"- Every instance was tight (rank {d}) at every level: no transition seen.")
        else:
            below = [lv for lv in tight_levels if lv < first_loose]
            obs.append(
                f"- Rank exactly {d} (tight) in every instance for levels "
                f"{', '.join(f'{lv:g}' for lv in below) or '(none)'}; the first level with a "
                f"non-tight instance is {first_loose:g}"
                + (
                    f", and from {min(all_loose):g} on no instance is tight."
                    if all_loose
                    else f"; even at the largest level {rows[-1]['level']:g} a fraction "
                    f"{rows[-1]['tight']:.2f} of the instances is still tight."
                )
            )
            obs.append(
                "- Mean rank per level: "
                + ", ".join(f"{r['level']:g}: {r['mean_rank']:.2f}" for r in rows)
                + "."
            )
        if any(r["conv"] < 1.0 for r in rows):
            obs.append(
                "- Some c-admm runs hit the iteration cap (converged column < 1): their rank "
                "is read from an inexact optimum."
            )
        lines += obs + [""]
    lines += [
        "Paper vs here: the paper's Fig. 3 shows rank exactly 2 below a noise threshold and "
        "rank > 2 above it. The observations above state, per setup, where the measured "
        "transition lies. The paper does not give the network of its Fig. 3; setup A reuses "
        "the network of its Fig. 2.",
        "",
    ]
    md = out / "paper000_fig3.md"
    md.write_text("\n".join(lines).replace("TOTAL_WALL", f"{time.perf_counter() - t_start:.1f} s"))
    print(f"wrote {md} and {png} in {time.perf_counter() - t_start:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
