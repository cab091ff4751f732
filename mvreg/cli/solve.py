"""``mvreg solve`` (the global stage alone, on a patch problem) and ``mvreg make-problem``."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from mvreg.cli.common import SET_HELP, check_out_file, config_from, run_guarded

app = typer.Typer()


POLICIES = ("balanced", "theorem4")  # --rho NAME: rho 'auto' with that policy


@app.command(epilog="Example:  mvreg solve problem.npz --out result.json --rho auto --max-iter 500")
def solve(
    problem: Annotated[
        Path,
        typer.Argument(help="Patch problem .npz (coords, patch, node[, weight, patch_names])."),
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="result.json to write.")],
    solver: Annotated[
        str | None, typer.Option(help="reg-admm (default) or another registered solver.")
    ] = None,
    method: Annotated[
        str | None, typer.Option(help="auto (default) | dense | matrix-free.")
    ] = None,
    rho: Annotated[
        str | None,
        typer.Option(
            help="'auto' (default: reg_admm.rho_policy, 'balanced': lambda_max(C)/M, balanced "
            "down by the residuals; 'theorem4': paper 000's bound) or a number."
        ),
    ] = None,
    max_iter: Annotated[int | None, typer.Option(help="Iteration cap (default 500).")] = None,
    tol: Annotated[
        float | None, typer.Option(help="Relative residual tolerance (default 1e-6).")
    ] = None,
    allow_reflections: Annotated[
        bool, typer.Option(help="Solve over O(d) instead of SO(d).")
    ] = False,
    seed: Annotated[int | None, typer.Option(help="Seed of the iterative eigensolvers.")] = None,
    config: Annotated[
        Path | None, typer.Option(help="JSON/YAML config file; its 'solve' section is used.")
    ] = None,
    set_: Annotated[list[str] | None, typer.Option("--set", help=SET_HELP)] = None,
    force: Annotated[bool, typer.Option(help="Overwrite an existing result.")] = False,
):
    """Solve a patch problem: rotations, translations and a certificate of optimality.

    The options are shortcuts into the configuration's ``solve`` section (the same one
    ``register`` uses); ``--set solve.gpm.max_iter=50`` reaches every other setting.
    """

    def _run():
        from mvreg.io.poses import write_poses_json
        from mvreg.solver import load_problem
        from mvreg.solver import solve as solve_problem

        cfg = config_from(
            config,
            set_,
            **{
                "solve.solver": solver,
                "solve.method": method,
                "solve.rho": None if rho in POLICIES else rho,
                "solve.reg_admm.rho_policy": rho if rho in POLICIES else None,
                "solve.max_iter": max_iter,
                "solve.tol": tol,
                "solve.allow_reflections": allow_reflections or None,
                "seed": seed,
            },
        )
        check_out_file(out, force, inputs=(problem,))
        prob = load_problem(problem)
        res = solve_problem(prob, cfg.solve, seed=cfg.seed)
        write_poses_json(
            out,
            res.poses(),
            solver=res.to_dict(),
            certificate=res.certificate.to_dict() if res.certificate else None,
            problem={
                "file": str(problem),
                "d": prob.d,
                "patches": prob.num_patches,
                "nodes": prob.num_nodes,
                "observations": prob.num_observations,
            },
            config={"solve": cfg.solve.model_dump(mode="json"), "seed": cfg.seed},
        )
        typer.echo(res.summary())
        return res

    run_guarded(_run)


@app.command(
    "make-problem", epilog="Example:  mvreg make-problem --patches 1000 --noise 0.01 --out p.npz"
)
def make_problem_cmd(
    out: Annotated[Path, typer.Option("--out", "-o", help=".npz to write.")],
    patches: Annotated[int, typer.Option(min=2, help="Number of patches M.")] = 100,
    d: Annotated[int, typer.Option(min=2, max=3, help="Dimension.")] = 3,
    degree: Annotated[
        int | None,
        typer.Option(min=1, help="Mean number of overlapping patches (default 6, at most M-1)."),
    ] = None,
    nodes_per_pair: Annotated[
        int, typer.Option(min=1, help="Shared nodes per overlapping pair.")
    ] = 20,
    noise: Annotated[
        float, typer.Option(min=0.0, help="Noise std, fraction of patch size.")
    ] = 0.01,
    outliers: Annotated[
        float, typer.Option(min=0.0, max=1.0, help="Fraction of outlier observations.")
    ] = 0.0,
    seed: Annotated[int, typer.Option(min=0)] = 0,
    force: Annotated[bool, typer.Option(help="Overwrite an existing file.")] = False,
):
    """Write a synthetic patch problem (and its ground truth beside it)."""

    def _run():
        from data_synth.problems import make_problem
        from mvreg.errors import InputError
        from mvreg.geometry import make_transform
        from mvreg.io.poses import write_poses_json
        from mvreg.solver import save_problem

        check_out_file(out, force)
        if degree is not None and degree > patches - 1:
            raise InputError(
                f"--degree {degree}: a patch overlaps at most the {patches - 1} others "
                f"(--patches {patches})"
            )
        deg = min(6, patches - 1) if degree is None else degree
        prob, truth = make_problem(patches, d, deg, nodes_per_pair, noise, outliers, seed=seed)
        save_problem(out, prob)
        gt = out.with_name(out.stem + "_truth.json")
        write_poses_json(
            gt,
            {
                n: make_transform(r, t)
                for n, r, t in zip(
                    prob.patch_names, truth.rotations, truth.translations, strict=True
                )
            },
            generator={
                "patches": patches,
                "d": d,
                "degree": deg,
                "nodes_per_pair": nodes_per_pair,
                "noise": noise,
                "outliers": outliers,
                "seed": seed,
            },
        )
        typer.echo(f"wrote {out} ({prob}) and {gt}")

    run_guarded(_run)
