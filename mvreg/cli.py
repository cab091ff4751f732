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


class RichProgress:
    """Progress bars for the pipeline stages (the pipeline calls stage/advance/done)."""

    def __init__(self):
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
        )

        self._p = Progress(
            TextColumn("{task.description:>22}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            transient=False,
        )
        self._task = None
        self._p.start()

    def stage(self, name: str, total: int | None = None) -> None:
        if self._task is not None:
            t = self._p.tasks[self._task]
            self._p.update(self._task, completed=t.total or 1, total=t.total or 1)
        self._task = self._p.add_task(name, total=total if total else 1)

    def advance(self, n: int = 1) -> None:
        if self._task is not None:
            self._p.advance(self._task, n)

    def done(self) -> None:
        self.stage("done", 1)
        self._p.advance(self._task, 1)
        self._p.stop()


def _summary_table(reg) -> None:
    from rich.console import Console
    from rich.table import Table

    c = reg.solve.certificate if reg.solve is not None else None
    t = Table(title="mvreg register", show_header=False)
    t.add_row("scans", f"{len(reg.scan_names)} ({len(reg.T_world_scan)} registered)")
    if reg.unregistered:
        t.add_row("[red]unregistered[/]", ", ".join(reg.unregistered))
    ver = getattr(reg, "verification", None) or {}
    if ver:
        n_ok = sum(1 for v in ver.values() if v["status"] == "verified")
        t.add_row(
            "verified poses",
            f"verified: {n_ok} of {len(reg.scan_names)}"
            + ("" if n_ok == len(reg.scan_names) else " [red](partial result)[/]"),
        )
        for name, v in ver.items():
            if v["status"] in ("unverified", "undetermined"):
                t.add_row(f"[red]{v['status']}[/]", f"{name}: {v['reason']}")
                if v["degenerate_dof"]:
                    t.add_row("", f"  free: {v['degenerate_dof']}")
    accepted = [p for p in reg.pairs if p["accepted"]]
    bad = [p for p in accepted if p["final_weight"] == 0.0]
    t.add_row(
        "pairs", f"{len(reg.pairs)} tried, {len(accepted)} accepted, {len(bad)} down-weighted to 0"
    )
    if c is not None:
        t.add_row(
            "global solve certified optimal for the accepted pairs",
            "yes" if c.certified else "[red]no[/]",
        )
    j = getattr(reg, "joint_icp", None)
    if j:
        moved = (
            "moved the poses of the certified solve by at most "
            f"{j['max_rotation_change_deg']:.3f} deg, {j['max_point_move_voxels']:.2f} voxels"
        )
        t.add_row(
            "joint point-to-plane ICP",
            f"{j['iterations']} iterations, {moved}"
            if j["accepted"]
            else f"[yellow]not kept[/] (would have {moved})",
        )
    if reg.overlap and reg.overlap["median"] is not None:
        t.add_row(
            "overlap residual",
            f"median {reg.overlap['median']:.4g}, mean {reg.overlap['mean']:.4g} (data units)",
        )
    if reg.truth_errors:
        e = reg.truth_errors
        t.add_row(
            "vs ground truth",
            f"rotation max {e['rotation_deg_max']:.3f} deg, "
            f"translation max {e['translation_max']:.4g} at the frame origins, "
            f"{e['translation_at_centroid_max']:.4g} at the scan centroids",
        )
    t.add_row("time", f"{reg.timings['total']:.2f} s")
    Console(stderr=True).print(t)


@app.command(epilog="Example:  mvreg register scans/ --out result/ --refine 3 --seed 0")
def register(
    folder: Annotated[
        Path, typer.Argument(help="Folder of scans (PLY, PCD, XYZ, XYZN, XYZRGB, PTS, NPY).")
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")],
    voxel_size: Annotated[
        float | None,
        typer.Option(
            min=0.0, help="Feature voxel size (data units); default: derived from the data."
        ),
    ] = None,
    solver: Annotated[str | None, typer.Option(help="Global solver (default reg-admm).")] = None,
    refine: Annotated[
        int | None, typer.Option(min=0, help="Rounds of multiview ICP refinement (default 3).")
    ] = None,
    seed: Annotated[int | None, typer.Option(help="Seed: same seed, same poses.")] = None,
    config: Annotated[
        Path | None, typer.Option(help="JSON/YAML config file (stage -> settings).")
    ] = None,
    rrd: Annotated[
        Path | None,
        typer.Option(help="Where to write the rerun recording (default OUT/recording.rrd)."),
    ] = None,
    no_rrd: Annotated[bool, typer.Option("--no-rrd", help="Do not write a recording.")] = False,
    spawn: Annotated[bool, typer.Option(help="Open the rerun viewer (when installed).")] = False,
    sequence: Annotated[
        bool,
        typer.Option(
            "--sequence",
            help="Scans taken one after another by a moving LiDAR: KISS-ICP odometry, "
            "loop closures, then the global solve (timestamps from timestamps.txt or names).",
        ),
    ] = False,
    force: Annotated[bool, typer.Option(help="Overwrite existing results in OUT.")] = False,
):
    """Register a folder of raw scans: poses, merged cloud, report and a rerun recording."""

    def _run():
        code = register_folder(
            folder,
            out,
            voxel_size=voxel_size,
            solver=solver,
            refine=refine,
            seed=seed,
            config=config,
            rrd=rrd,
            no_rrd=no_rrd,
            spawn=spawn,
            force=force,
            sequence=sequence,
        )
        raise typer.Exit(code)

    run_guarded(_run)


def register_folder(
    folder,
    out,
    *,
    voxel_size=None,
    solver=None,
    refine=None,
    seed=None,
    config=None,
    rrd=None,
    no_rrd=False,
    spawn=False,
    force=False,
    progress=True,
    truth=None,
    sequence=False,
):
    """The body of `mvreg register` (also used by `mvreg demo`). Returns the exit code."""
    from mvreg.config import load_config
    from mvreg.errors import ConfigError, OutputExistsError
    from mvreg.io.writers import prepare_output, residual_heatmap, write_registration
    from mvreg.pipeline import register as run_register

    if sequence:
        from mvreg.sequence import register_sequence as run_register
    from mvreg.solver import SOLVERS
    from mvreg.viz import make_recorder

    if voxel_size is not None and voxel_size <= 0:
        raise ConfigError(f"--voxel-size must be positive, got {voxel_size}")
    if solver is not None and solver not in SOLVERS:
        raise ConfigError(f"unknown solver '{solver}' (choose from {', '.join(SOLVERS)})")
    cfg = load_config(
        config,
        **{
            "preprocess.voxel_size": voxel_size,
            "solve.solver": solver,
            "refine.rounds": refine,
            "seed": seed,
        },
    )
    out = prepare_output(out, force)
    rrd_path = None if no_rrd else (rrd if rrd is not None else out / "recording.rrd")
    if rrd is not None and rrd.exists() and not force:
        raise OutputExistsError(f"{rrd} exists (use --force to overwrite)")
    rec = make_recorder(rrd_path, spawn=spawn, recording_id=f"mvreg-{cfg.seed}")
    for w in getattr(rec, "warnings", []):
        typer.echo(f"mvreg: warning: {w}", err=True)
    with rec:
        reg = run_register(
            folder, cfg, recorder=rec, progress=RichProgress() if progress else None, truth=truth
        )
        if reg.T_world_scan:
            pts, res = residual_heatmap(reg)
            rec.log_residual_heatmap(pts, res)
        paths = write_registration(reg, out)
    _summary_table(reg)
    typer.echo(
        f"wrote {', '.join(str(p) for p in paths.values() if p.exists())}"
        + (f", {rrd_path}" if rrd_path is not None else "")
    )
    partial = reg.unregistered or getattr(reg, "unverified", []) or getattr(reg, "undetermined", [])
    return 3 if partial else 0


@app.command(epilog="Example:  mvreg demo --out demo_out --views 12 --seed 0")
def demo(
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for scans/ and result/.")] = Path(
        "demo_out"
    ),
    views: Annotated[int, typer.Option(min=2, help="Number of synthetic scans.")] = 12,
    noise: Annotated[
        float, typer.Option(min=0.0, help="Range noise, fraction of the object diagonal.")
    ] = 0.002,
    seed: Annotated[
        int, typer.Option(help="Seed of the object, views, noise and registration.")
    ] = 0,
    force: Annotated[bool, typer.Option(help="Overwrite an earlier demo in OUT.")] = False,
):
    """Synthesize the built-in object, register the scans, print errors against ground truth."""

    def _run():
        from data_synth import synthesize_scans
        from mvreg.io.writers import prepare_output

        scans_dir, result_dir = out / "scans", out / "result"
        prepare_output(result_dir, force)  # refuse before spending time
        typer.echo(f"synthesizing {views} scans of the built-in object -> {scans_dir}")
        synth = synthesize_scans(
            "builtin",
            scans_dir,
            views=views,
            noise=noise,
            seed=seed,
            random_frames=True,
            force=force,
        )
        code = register_folder(scans_dir, result_dir, seed=seed, force=force)
        import json

        report = json.loads((result_dir / "report.json").read_text())
        e = report["ground_truth_errors"]
        diag = synth.object_diagonal
        typer.echo(
            f"errors vs ground truth: rotation median {e['rotation_deg_median']:.4f} / max "
            f"{e['rotation_deg_max']:.4f} deg; translation median "
            f"{e['translation_median'] / diag * 100:.4f}% / max "
            f"{e['translation_max'] / diag * 100:.4f}% of the object diagonal at the frame "
            f"origins, max {e['translation_at_centroid_max'] / diag * 100:.4f}% at the scan "
            "centroids; "
            f"certified: {report['certificate']['certified']}"
            + (
                f" (then moved at most {j['max_rotation_change_deg']:.4f} deg by joint ICP)"
                if (j := report.get("joint_icp")) and j["accepted"]
                else ""
            )
        )
        typer.echo(f"open the recording with:  rerun {result_dir / 'recording.rrd'}")
        raise typer.Exit(code)

    run_guarded(_run)


@app.command("eval", epilog="Example:  mvreg eval result/ --truth scans/ground_truth.json")
def eval_cmd(
    out: Annotated[
        Path, typer.Argument(help="Output folder of `mvreg register` (or a poses.json).")
    ],
    truth: Annotated[Path, typer.Option(help="Ground-truth poses (mvreg.poses/1 JSON).")],
):
    """Errors of a registration against ground-truth poses (gauge-free)."""

    def _run():
        import numpy as np
        from rich.console import Console
        from rich.table import Table

        from mvreg.errors import InputError
        from mvreg.io.poses import read_poses_json
        from mvreg.metrics import pose_errors

        poses_path = out / "poses.json" if out.is_dir() else out
        est = read_poses_json(poses_path)
        tru = read_poses_json(truth)
        common = [n for n in est if n in tru]
        if len(common) < 2:
            raise InputError(f"{truth}: fewer than 2 scans in common with {poses_path}")
        err = pose_errors(np.stack([est[n] for n in common]), np.stack([tru[n] for n in common]))
        t = Table(title=f"{poses_path} vs {truth}")
        t.add_column("scan")
        t.add_column("rotation error (deg)", justify="right")
        t.add_column("translation error", justify="right")
        for n, r, tr in zip(common, err.rotation_deg, err.translation, strict=True):
            t.add_row(n, f"{r:.4f}", f"{tr:.6g}")
        Console().print(t)
        s = err.summary()
        typer.echo(
            f"rotation median {s['rotation_deg_median']:.4f} max {s['rotation_deg_max']:.4f} deg; "
            f"translation median {s['translation_median']:.6g} max {s['translation_max']:.6g}"
        )
        missing = [n for n in tru if n not in est]
        if missing:
            typer.echo(f"not registered: {', '.join(missing)}", err=True)

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
