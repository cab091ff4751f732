"""The mvreg command line. Library code raises typed errors; only this module turns them
into one-line messages and exit codes (0 ok, 2 bad input, 3 scans unregistered, 4 failure).
Heavy imports happen inside the commands so that `mvreg --help` is instant.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

app = typer.Typer(
    name="mvreg",
    help="Global multiview registration of 3D scans, with certificates of optimality.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    rich_markup_mode="rich",
)
_state = {"debug": False}


def _version(value: bool):
    if not value:
        return
    import numpy
    import open3d
    import rerun
    import scipy

    from mvreg import __version__

    typer.echo(
        f"mvreg {__version__} (numpy {numpy.__version__}, scipy {scipy.__version__}, "
        f"open3d {open3d.__version__}, rerun {rerun.__version__})"
    )
    raise typer.Exit(0)


@app.callback()
def main(
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_version, is_eager=True, help="Versions (loads open3d)."
        ),
    ] = False,
    debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks on errors.")] = False,
):
    """mvreg: register many partial 3D scans into one frame, globally (REG-ADMM)."""
    _state["debug"] = debug


def fail(exc: BaseException) -> typer.Exit:
    """Print a one-line message for a library error; return the Exit to raise."""
    from mvreg.errors import MvregError

    if _state["debug"]:
        raise exc
    code = exc.exit_code if isinstance(exc, MvregError) else 4
    msg = str(exc) if isinstance(exc, MvregError) else f"{type(exc).__name__}: {exc}"
    typer.echo(f"mvreg: error: {msg}", err=True)
    return typer.Exit(code)


def run_guarded(fn, *args, **kwargs):
    """Call fn; turn MvregError (and, without --debug, anything else) into an exit code."""
    from mvreg.errors import MvregError

    try:
        return fn(*args, **kwargs)
    except typer.Exit:
        raise
    except MvregError as e:
        raise fail(e) from None
    except KeyboardInterrupt:
        typer.echo("mvreg: interrupted", err=True)
        raise typer.Exit(130) from None
    except Exception as e:  # noqa: BLE001 - last resort: one line, unless --debug
        raise fail(e) from None


def parse_rho(value: str) -> str | float:
    if value == "auto":
        return value
    try:
        rho = float(value)
    except ValueError:
        raise typer.BadParameter(f"'{value}' is not 'auto' or a number") from None
    if not rho > 0:
        raise typer.BadParameter(f"rho must be positive, got {value}")
    return rho


def _check_out_file(path: Path, force: bool):
    from mvreg.errors import OutputExistsError

    if path.exists() and not force:
        raise OutputExistsError(f"{path} exists (use --force to overwrite)")


@app.command(epilog="Example:  mvreg solve problem.npz --out result.json --rho auto --max-iter 500")
def solve(
    problem: Annotated[
        Path,
        typer.Argument(help="Patch problem .npz (coords, patch, node[, weight, patch_names])."),
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="result.json to write.")],
    solver: Annotated[
        str, typer.Option(help="reg-admm (default) or another registered solver.")
    ] = "reg-admm",
    method: Annotated[str, typer.Option(help="auto | dense | matrix-free.")] = "auto",
    rho: Annotated[
        str,
        typer.Option(
            help="'auto' (Theorem 4, raised on oscillation) or a number.", parser=parse_rho
        ),
    ] = "auto",
    max_iter: Annotated[int, typer.Option(min=1, help="Iteration cap.")] = 500,
    tol: Annotated[float, typer.Option(help="Relative residual tolerance of REG-ADMM.")] = 1e-6,
    allow_reflections: Annotated[
        bool, typer.Option(help="Solve over O(d) instead of SO(d).")
    ] = False,
    seed: Annotated[int, typer.Option(help="Seed of the iterative eigensolvers.")] = 0,
    force: Annotated[bool, typer.Option(help="Overwrite an existing result.")] = False,
):
    """Solve a patch problem: rotations, translations and a certificate of optimality."""

    def _run():
        from mvreg.io.poses import write_poses_json
        from mvreg.solver import load_problem
        from mvreg.solver import solve as solve_problem

        _check_out_file(out, force)
        prob = load_problem(problem)
        res = solve_problem(
            prob,
            solver,
            method=method,
            rho=rho,
            max_iter=max_iter,
            tol=tol,
            allow_reflections=allow_reflections,
            seed=seed,
        )
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
            config={
                "solver": solver,
                "method": method,
                "rho": rho,
                "max_iter": max_iter,
                "tol": tol,
                "allow_reflections": allow_reflections,
                "seed": seed,
            },
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
    degree: Annotated[int, typer.Option(min=1, help="Mean number of overlapping patches.")] = 6,
    nodes_per_pair: Annotated[
        int, typer.Option(min=1, help="Shared nodes per overlapping pair.")
    ] = 20,
    noise: Annotated[
        float, typer.Option(min=0.0, help="Noise std, fraction of patch size.")
    ] = 0.01,
    outliers: Annotated[
        float, typer.Option(min=0.0, max=1.0, help="Fraction of outlier observations.")
    ] = 0.0,
    seed: Annotated[int, typer.Option()] = 0,
    force: Annotated[bool, typer.Option(help="Overwrite an existing file.")] = False,
):
    """Write a synthetic patch problem (and its ground truth beside it)."""

    def _run():
        from data_synth.problems import make_problem
        from mvreg.geometry import make_transform
        from mvreg.io.poses import write_poses_json
        from mvreg.solver import save_problem

        _check_out_file(out, force)
        prob, truth = make_problem(patches, d, degree, nodes_per_pair, noise, outliers, seed=seed)
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
                "degree": degree,
                "nodes_per_pair": nodes_per_pair,
                "noise": noise,
                "outliers": outliers,
                "seed": seed,
            },
        )
        typer.echo(f"wrote {out} ({prob}) and {gt}")

    run_guarded(_run)


def _register_optional_commands():
    """Commands that live beside their stage (data_synth, the register pipeline)."""
    try:
        from data_synth.cli import synth_command
    except ImportError:  # pragma: no cover - data_synth ships with mvreg
        return
    app.command(
        "synth", epilog="Example:  mvreg synth builtin --out scans/ --views 12 --noise 0.002"
    )(synth_command)


_register_optional_commands()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
