"""Paper 000 (Singh & Chaudhury), Fig. 2: REG-ADMM's dependence on rho at three noise levels.

Setup of the paper (Sec. 1.4): d = 2, a network of 10 nodes, 3 patches that each hold all 10
nodes, every patch's local frame a random rotation of the global one, iid Gaussian noise of
variance sigma^2 on the local coordinates. REG-ADMM (eq. 7) is run from a given H0 with
Lambda0 = 0 and a fixed rho, without Newton polish (``solve(..., polish=False)``), and
Tr(C G^k) is plotted against k.

Noise levels: 0 (clean), "low" and "high" in the paper's sense (Sec. 1.5): low = the convex
relaxation C-SDP is tight (rank of its optimum = d, checked with c-admm), high = not tight.
The instance of each noisy level is the first seed >= --seed whose C-SDP rank is d (low) or
> d (high).

rho: mvreg normalizes the data (patch centroids removed, one global scale s = RMS of the
centred coordinates), so its C is C_data / s^2 and REG-ADMM with rho on the normalized C is
the same iteration as rho * s^2 on the data's C. "rho = 1" of the paper is given in the
data's units (nodes in the unit square) and converted; the other values are in mvreg's
normalized units.

    python scripts/paper000_fig2.py                # full (2000 iterations per run)
    python scripts/paper000_fig2.py --quick        # 300 iterations, for the smoke test
    python scripts/paper000_fig2.py --out DIR      # write DIR/paper000_fig2.{md,png}
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from bench.common import ROOT, blas_threads, machine_info
from mvreg.geometry import random_rotations
from mvreg.solver import PatchProblem, RegOperator, solve
from mvreg.solver.c_admm import c_admm
from mvreg.solver.reg_admm import theorem4_rho
from mvreg.solver.spectral import spectrum

N_NODES, M, D = 10, 3, 2
SENS_RHOS = (0.1, 1.0, 10.0, 100.0)


def build(var: float, seed: int) -> tuple[PatchProblem, np.ndarray]:
    """10 nodes uniform in the unit square; 3 patches holding all of them."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.0, 1.0, size=(N_NODES, D))
    rot = random_rotations(rng, M, D)
    coords, patch, node = [], [], []
    for i in range(M):
        x = z @ rot[i]  # x = R_i^T z (the global frame rotated)
        if var > 0:
            x = x + math.sqrt(var) * rng.standard_normal(x.shape)
        coords.append(x)
        patch += [i] * N_NODES
        node += list(range(N_NODES))
    return PatchProblem(np.vstack(coords), np.array(patch), np.array(node)), rot


def sdp_rank(problem: PatchProblem) -> tuple[int, float]:
    op = RegOperator(problem)
    res = c_admm(
        op.dense(), D, random_rotations(np.random.default_rng(0), M, D), tol=1e-10, max_iter=20000
    )
    return res.rank, res.upper * op.norm.scale**2


def find_instance(var: float, want_tight: bool, seed0: int, tries: int):
    for seed in range(seed0, seed0 + tries):
        problem, rot = build(var, seed)
        rank, sdp = sdp_rank(problem)
        if (rank == D) == want_tight:
            return problem, rot, seed, rank, sdp
    raise RuntimeError(f"no {'tight' if want_tight else 'non-tight'} instance at variance {var}")


def run(problem, rho, H0, max_iter):
    t0 = time.perf_counter()
    res = solve(
        problem,
        solver="reg-admm",
        polish=False,
        rho=rho,
        init=H0,
        max_iter=max_iter,
        tol=1e-10,
    )
    wall = time.perf_counter() - t0
    f = np.array([h["objective"] for h in res.history])
    pr = np.array([h["primal_residual"] for h in res.history])
    tail = max(1, len(f) // 5)
    # Non-attenuating: the primal residual's peak over the last 20% of the run is at least
    # half its peak over the 20% before (a converging run shrinks it by orders of magnitude).
    prev = pr[-2 * tail : -tail] if len(pr) >= 2 * tail else pr[:tail]
    attenuation = float(pr[-tail:].max() / max(prev.max(), 1e-300))
    # Turns of Tr(C G^k) over the last 20% (0 for a monotone approach to the limit).
    turns = int(np.sum(np.diff(np.sign(np.diff(f[-tail:]))) != 0)) if tail > 2 else 0
    return {
        "turns": turns,
        "attenuation": attenuation,
        "res": res,
        "f": f,
        "pr": pr,
        "iterations": len(f),
        "residuals_converged": bool(res.stats.get("residuals_converged")),
        "f_last": float(f[-1]),
        "f_tail_min": float(f[-tail:].min()),
        "f_tail_max": float(f[-tail:].max()),
        "pr_last": float(pr[-1]),
        "pr_tail_max": float(pr[-tail:].max()),
        "reg_cost": float(res.objective),
        "certified": bool(res.certified),
        "wall": wall,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="300 iterations per run")
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks"))
    ap.add_argument("--seed", type=int, default=0, help="first instance seed")
    ap.add_argument("--init-seed", type=int, default=100, help="seed of H0")
    ap.add_argument("--max-iter", type=int, default=None)
    ap.add_argument("--low", type=float, default=0.01, help="low noise variance")
    ap.add_argument("--high", type=float, default=0.3, help="high noise variance")
    args = ap.parse_args(argv)
    max_iter = args.max_iter or (300 if args.quick else 2000)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()

    # H0 = O0^T O0 from random orthogonal blocks, the second one a reflection: an arbitrary
    # feasible start (REG-SDP, like the paper, does not distinguish SO(2) from O(2)).
    H0 = random_rotations(np.random.default_rng(args.init_seed), M, D)
    H0[1, :, 0] *= -1.0

    clean, _ = build(0.0, args.seed)
    low, _, low_seed, low_rank, low_sdp = find_instance(args.low, True, args.seed, 50)
    high, _, high_seed, high_rank, high_sdp = find_instance(args.high, False, args.seed, 200)
    levels = [
        ("clean", 0.0, clean, args.seed, *sdp_rank(clean)),
        ("low", args.low, low, low_seed, low_rank, low_sdp),
        ("high", args.high, high, high_seed, high_rank, high_sdp),
    ]
    small, large = 0.01, 10.0
    panels = []
    for name, var, problem, seed, rank, sdp in levels:
        op = RegOperator(problem)
        spec = spectrum(op, dense=True)
        s2 = op.norm.scale**2
        th4 = theorem4_rho(float(spec.smallest[D]), M, D)
        if name == "clean":
            rhos = [("rho = 1 (data units)", 1.0 / s2), ("rho = Theorem 4", th4)]
        else:
            rhos = [(f"small rho = {small:g}", small), (f"large rho = {large:g}", large)]
        runs = [(label, rho, run(problem, rho, H0, max_iter)) for label, rho in rhos]
        autos = []
        for init_name, init in (("H0", H0), ("spectral", "spectral")):
            t0 = time.perf_counter()
            r = solve(problem, solver="reg-admm", init=init)  # rho="auto", polish default
            autos.append((init_name, r, time.perf_counter() - t0))
        panels.append(
            dict(
                name=name,
                var=var,
                seed=seed,
                rank=rank,
                sdp=sdp,
                s2=s2,
                th4=th4,
                runs=runs,
                autos=autos,
            )
        )

    # Start sensitivity on the clean instance (cheap: M = 3): final REG cost per start.
    sens = {}
    for start_name, flip in (("3 proper rotations", False), ("block 2 reflected", True)):
        sens[start_name] = {}
        for rho in SENS_RHOS:
            costs = []
            for s in range(3):
                O0 = random_rotations(np.random.default_rng(args.init_seed + s), M, D)
                if flip:
                    O0[1, :, 0] *= -1.0
                r = solve(
                    clean,
                    solver="reg-admm",
                    polish=False,
                    rho=rho,
                    init=O0,
                    max_iter=max_iter,
                    tol=1e-10,
                )
                costs.append(r.objective)
            sens[start_name][rho] = costs

    # ------------------------------------------------------------------ plot
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(14, 7.5))
    for j, p in enumerate(panels):
        ax, axr = axes[0, j], axes[1, j]
        for label, rho, r in p["runs"]:
            k = np.arange(1, r["iterations"] + 1)
            f = r["f"]
            if p["name"] == "clean":
                ax.semilogy(k, np.maximum(f, 1e-16), label=f"{label} ({rho:.3g})")
            else:
                ax.plot(k, f, label=f"{label}")
            axr.semilogy(k, np.maximum(r["pr"], 1e-16), label=label)
        if p["name"] != "clean":
            ax.axhline(p["sdp"], color="k", ls=":", lw=1, label="C-SDP optimum")
        ax.set_title(f"{p['name']} (variance {p['var']:g}, C-SDP rank {p['rank']})")
        ax.set_xlabel("iteration")
        ax.set_ylabel("Tr(C G^k)")
        ax.legend(fontsize=8)
        axr.set_xlabel("iteration")
        axr.set_ylabel("primal residual ||bd(G) - I|| / sqrt(Md)")
        axr.legend(fontsize=8)
    fig.suptitle("Paper 000 Fig. 2 reproduced: REG-ADMM (eq. 7), d = 2, 10 nodes, 3 patches")
    fig.tight_layout()
    png = out / "paper000_fig2.png"
    fig.savefig(png, dpi=110)
    plt.close(fig)

    # ------------------------------------------------------------------ markdown
    lines = ["# Paper 000 Fig. 2: REG-ADMM vs rho at three noise levels", ""]
    lines += machine_info(
        f"(threadpoolctl: {blas_threads()}); the machine's 2 cores are shared with other jobs"
    )
    lines += [
        "- total wall time: TOTAL_WALL",
        "",
        "Setup: d = 2, 10 nodes uniform in the unit square, 3 patches each holding all 10 "
        "nodes, each patch frame a random rotation of the global one, iid Gaussian noise of the "
        "given variance on the local coordinates. REG-ADMM eq. (7) from H0 = O0^T O0, "
        "Lambda0 = 0, fixed rho, `solve(..., polish=False, tol=1e-10, "
        f"max_iter={max_iter})`. O0: random orthogonal blocks, block 2 a reflection "
        f"(init seed {args.init_seed}). Noisy instances: first seed whose C-SDP optimum "
        "(c-admm, tol 1e-10) has rank d (low) / > d (high). rho values are in mvreg's "
        "normalized units (C / s^2); 'rho = 1 (data units)' is 1 / s^2.",
        "",
        f"![REG-ADMM objective vs iteration]({png.name})",
        "",
        "| noise | variance | seed | C-SDP rank | C-SDP optimum | rho | rho (data units) | "
        "iterations | residuals converged | last Tr(CG) | Tr(CG) range, last 20% | "
        "primal residual max, last 20% | REG cost of rounded rotations | certified |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for p in panels:
        for label, rho, r in p["runs"]:
            lines.append(
                f"| {p['name']} | {p['var']:g} | {p['seed']} | {p['rank']} | {p['sdp']:.5g} | "
                f"{label}: {rho:.4g} | {rho * p['s2']:.4g} | {r['iterations']} | "
                f"{'yes' if r['residuals_converged'] else 'no'} | {r['f_last']:.5g} | "
                f"{r['f_tail_min']:.4g} .. {r['f_tail_max']:.4g} | {r['pr_tail_max']:.2e} | "
                f"{r['reg_cost']:.5g} | {'yes' if r['certified'] else 'no'} |"
            )
    lines += ["", "Observations (computed from the runs above):", ""]
    obs = []
    c = panels[0]
    (l1, _, r1), (l2, _, r2) = c["runs"]
    stuck = r1["reg_cost"] > 1e-6 and r1["residuals_converged"]
    obs.append(
        f"- Clean data, {l1}: REG-ADMM "
        + (
            "converged (residuals below 1e-10) to a fixed point with "
            if r1["residuals_converged"]
            else "did not reach the residual tolerance; "
        )
        + f"Tr(CG) = {r1['f_last']:.4g} while the optimum is 0"
        + (
            ": stuck at a local minimum, as in the paper's Fig. 2a."
            if stuck
            else (
                ": it reached the global optimum, unlike the paper's Fig. 2a."
                if r1["reg_cost"] <= 1e-6
                else "."
            )
        )
    )
    obs.append(
        f"- Clean data, {l2} ({r2['res'].rho_initial:.4g}): final Tr(CG) = {r2['f_last']:.3g} "
        f"after {r2['iterations']} iterations, REG cost {r2['reg_cost']:.3g}"
        + (
            " : the global optimum, as Theorem 4 guarantees."
            if r2["reg_cost"] < 1e-8
            else " : NOT the global optimum, contrary to Theorem 4."
        )
    )
    for p in panels[1:]:
        for label, _, r in p["runs"]:
            osc = (
                not r["residuals_converged"]
                and r["pr_tail_max"] > 1e-3
                and r["attenuation"] >= 0.5
                and r["turns"] >= 2
            )
            local = r["residuals_converged"] and r["f_last"] > p["sdp"] * (1 + 1e-4) + 1e-9
            obs.append(
                f"- {p['name']} noise, {label}: "
                + (
                    f"non-attenuating oscillation: after {r['iterations']} iterations the "
                    f"primal residual is still up to {r['pr_tail_max']:.2g} and Tr(CG) swings "
                    f"between {r['f_tail_min']:.4g} and {r['f_tail_max']:.4g}, changing direction "
                    f"{r['turns']} times in the last 20% of the run (peak residual ratio last "
                    f"20% / previous 20%: {r['attenuation']:.2f})."
                    if osc
                    else (
                        f"converged in {r['iterations']} iterations to Tr(CG) = "
                        f"{r['f_last']:.5g} (REG cost of the rounded rotations "
                        f"{r['reg_cost']:.5g}, certified: {'yes' if r['certified'] else 'no'})"
                        + (
                            f"; the C-SDP optimum {p['sdp']:.5g} is only a lower bound here "
                            f"(rank {p['rank']} > d: not tight)."
                            if p["rank"] > D
                            else f"; the C-SDP optimum is {p['sdp']:.5g} and the relaxation is "
                            "tight, so this limit is a worse stationary point (the limit depends "
                            "on rho)."
                            if local
                            else f"; the C-SDP optimum is {p['sdp']:.5g}."
                        )
                        if r["residuals_converged"]
                        else f"not converged in {r['iterations']} iterations (primal residual "
                        f"{r['pr_last']:.2g}; peak ratio last 20% / previous 20% "
                        f"{r['attenuation']:.2f}; Tr(CG) changed direction {r['turns']} times in "
                        "the last 20%)."
                    )
                )
            )
    lines += obs
    lines += [
        "",
        "Paper vs here: the paper shows (a) rho = 1 stuck and the Theorem-4 rho converging on "
        "clean data, (b) no oscillation at low noise, (c) non-attenuating oscillation for "
        "small rho at high noise. The verdicts above say, run by run, whether this "
        "reproduction shows the same. Caveat: the paper's rho = 1 refers to its own "
        "(unstated) coordinate scale; we use nodes in the unit square.",
        "",
        "Start sensitivity (table at the end, clean instance, 3 starts per cell): "
        + "; ".join(
            f"from {name}, the global optimum (REG cost < 1e-8) was reached for rho in "
            + "{"
            + (", ".join(f"{rho:g}" for rho, cs in row.items() if max(cs) < 1e-8) or "none")
            + "}"
            + (
                " and missed for rho in {"
                + ", ".join(f"{rho:g}" for rho, cs in row.items() if max(cs) >= 1e-8)
                + "}"
                if any(max(cs) >= 1e-8 for cs in row.values())
                else ""
            )
            for name, row in sens.items()
        )
        + " (missed = REG cost >= 1e-8 at the iteration cap: a stuck fixed point or slow "
        "convergence). In our runs getting stuck needed a start whose blocks disagree in "
        "orientation (REG-SDP, like the paper, works over O(d)), as the H0 above does.",
        "",
        '## rho = "auto" (Theorem 4 start, doubled on stalls, Newton polish, stop when certified)',
        "",
        "| noise | init | iterations | rho initial -> final | stopped by | REG cost | certified |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for p in panels:
        for init_name, r, _ in p["autos"]:
            lines.append(
                f"| {p['name']} | {init_name} | {r.iterations} | {r.rho_initial:.4g} -> "
                f"{r.rho_final:.4g} | {r.stats.get('stopped_by')} | {r.objective:.5g} | "
                f"{'yes' if r.certified else 'no'} |"
            )
    lines += [""]
    for p in panels:
        best = min(r.objective for _, r, _ in p["autos"])
        cert = [n for n, r, _ in p["autos"] if r.certified]
        lines.append(
            f"- {p['name']}: rho=auto reached REG cost {best:.5g}"
            + (
                f", certified from {' and '.join(cert)}."
                if cert
                else " but could not certify it: the C-SDP relaxation is not tight here (rank "
                f"{p['rank']}), so the dual certificate cannot exist (paper 000 Lemma 2)."
            )
        )

    lines += [
        "",
        f"## Start sensitivity on the clean instance (final REG cost, {max_iter} iterations max)",
        "",
        "| start | " + " | ".join(f"rho = {v:g}" for v in SENS_RHOS) + " |",
        "| --- | --- | --- | --- | --- |",
    ]
    for start_name, row in sens.items():
        lines.append(
            f"| {start_name} | "
            + " | ".join(", ".join(f"{c:.2g}" for c in cs) for cs in row.values())
            + " |"
        )
    lines += ["", "(three starts per cell; 0 is the global optimum.)", ""]
    md = out / "paper000_fig2.md"
    text = "\n".join(lines).replace("TOTAL_WALL", f"{time.perf_counter() - t_start:.1f} s")
    md.write_text(text)
    start = lines.index("Observations (computed from the runs above):")
    print("\n".join(lines[start : start + 9]))
    print(f"wrote {md} and {png} in {time.perf_counter() - t_start:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
