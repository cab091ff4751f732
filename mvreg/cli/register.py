"""``mvreg register``, ``mvreg demo`` and ``mvreg eval``: options map onto the configuration
(``mvreg.config``), validated there once; everything else through ``--set``."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated

import typer

from mvreg.cli.common import SET_HELP, RichProgress, config_from, run_guarded

app = typer.Typer()


@app.command(
    epilog="Examples:  mvreg register scans/ --out result/ --refine 3 --seed 0\n\n"
    "mvreg register scans/ --out result/ --set align.ransac_max_iterations=8000\n\n"
    "mvreg register scans/ --out result/ --workers 4   (a local Dask cluster)"
)
def register(
    folder: Annotated[
        Path, typer.Argument(help="Folder of scans (PLY, PCD, XYZ, XYZN, XYZRGB, PTS, NPY).")
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")],
    voxel_size: Annotated[
        float | None,
        typer.Option(help="Feature voxel size (data units); default: derived from the data."),
    ] = None,
    solver: Annotated[str | None, typer.Option(help="Global solver (default reg-admm).")] = None,
    refine: Annotated[
        int | None, typer.Option(help="Rounds of multiview ICP refinement (default 3).")
    ] = None,
    seed: Annotated[int | None, typer.Option(help="Seed: same seed, same poses.")] = None,
    threads: Annotated[
        int | None,
        typer.Option(help="In-process threads for per-scan and per-pair work (default 2)."),
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option(
            help="Start a local Dask cluster of N worker processes for preprocessing and "
            "pairwise alignment (default: none, in-process threads)."
        ),
    ] = None,
    scheduler: Annotated[
        str | None,
        typer.Option(
            help="Run preprocessing and pairwise alignment on a running Dask cluster: the "
            "scheduler's address, e.g. tcp://10.0.0.5:8786."
        ),
    ] = None,
    config: Annotated[
        Path | None, typer.Option(help="JSON/YAML config file (stage -> settings).")
    ] = None,
    set_: Annotated[list[str] | None, typer.Option("--set", help=SET_HELP)] = None,
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
        cfg = config_from(
            config,
            set_,
            **{
                "preprocess.voxel_size": voxel_size,
                "solve.solver": solver,
                "refine.rounds": refine,
                "seed": seed,
                "threads": threads,
                "workers": workers,
                "scheduler": scheduler,
            },
        )
        code = register_folder(
            folder, out, cfg, rrd=rrd, no_rrd=no_rrd, spawn=spawn, force=force, sequence=sequence
        )
        raise typer.Exit(code)

    run_guarded(_run)


def warn(message: str) -> None:
    typer.echo(f"mvreg: warning: {message}", err=True)


def some(names: list[str], k: int = 5) -> str:
    """The first ``k`` names, and how many there are when more."""
    return ", ".join(names[:k]) + (f", ... ({len(names)} in all)" if len(names) > k else "")


def print_input_warnings(reg) -> None:
    """One warning line per thing the input lost: points dropped from a scan (NaN/inf
    coordinates, far strays), files not read, scans left out, sequence warnings."""
    from mvreg.io.loaders import display_path

    for scan in getattr(reg, "scans", None) or []:
        for count, what in (
            (scan.num_dropped_nonfinite, "with a NaN or infinite coordinate"),
            (getattr(scan, "num_dropped_far", 0), "far from the rest (strays)"),
        ):
            if count:
                where = display_path(scan.path) + (
                    "" if scan.path.name == scan.name else f" ({scan.name})"
                )
                typer.echo(f"mvreg: warning: {where}: {count} points {what} left out", err=True)
    for s in reg.skipped_files:
        typer.echo(f"mvreg: warning: {s['file']}: not read ({s['reason']})", err=True)
    for s in reg.rejected_scans:
        scan = "" if s["scan"] == s["file"] else f" (scan {s['scan']})"
        typer.echo(f"mvreg: warning: {s['file']}{scan}: not registered: {s['reason']}", err=True)
    missing = getattr(reg, "truth_without_scan", [])
    if missing:
        warn(f"ground truth: poses of scans not in the input (not evaluated): {some(missing)}")
    for w in (getattr(reg, "sequence", None) or {}).get("warnings", []):
        typer.echo(f"mvreg: warning: {w}", err=True)


def check_rrd_path(rrd: Path, folder, out, force: bool) -> None:
    """Refuse a --rrd that would overwrite an input or another result in OUT (even with
    --force), or a folder."""
    from mvreg.errors import InputError, OutputExistsError
    from mvreg.io.output_folder import RESULT_FILES

    if not str(rrd).strip():
        raise InputError("--rrd '': give a file name")
    if rrd.is_dir():
        raise InputError(f"--rrd {rrd}: is a folder; give a file name")
    target, inp = rrd.resolve(), Path(folder).resolve()
    if target == inp or inp in target.parents:
        raise InputError(f"--rrd {rrd}: is inside the input folder {folder}; choose another")
    if target.parent == Path(out).resolve() and target.name in RESULT_FILES:
        if target.name != "recording.rrd":
            raise InputError(f"--rrd {rrd}: is the result file {target.name} of --out {out}")
    if rrd.exists() and not force:
        raise OutputExistsError(f"{rrd} exists (use --force to overwrite)")


def register_folder(
    folder,
    out,
    cfg,
    *,
    rrd=None,
    no_rrd=False,
    spawn=False,
    force=False,
    progress=True,
    truth=None,
    sequence=False,
):
    """The body of `mvreg register` (also used by `mvreg demo`). Returns the exit code."""
    from mvreg.io.output_folder import OutputFolder
    from mvreg.io.writers import residual_heatmap, write_registration
    from mvreg.viz import make_recorder

    if sequence:
        from mvreg.sequence import register_sequence as run_register
    else:
        from mvreg.pipeline import register as run_register

    output = OutputFolder(out, force=force, inputs=[folder])
    output.check()  # refuse before spending time
    if rrd is not None and not no_rrd:
        check_rrd_path(Path(rrd), folder, out, force)
    with output as staging:  # written into staging, swapped in on success
        rrd_path = None if no_rrd else output.staged(rrd or staging / "recording.rrd")
        rec = make_recorder(rrd_path, spawn=spawn, recording_id=f"mvreg-{cfg.seed}")
        for w in getattr(rec, "warnings", []):
            typer.echo(f"mvreg: warning: {w}", err=True)
        bars = RichProgress() if progress else None
        with rec:
            try:
                reg = run_register(folder, cfg, recorder=rec, progress=bars, truth=truth)
            finally:
                if bars is not None:
                    bars.stop()
            if reg.T_world_scan:
                pts, res = residual_heatmap(reg)
                rec.log_residual_heatmap(pts, res)
            paths = write_registration(reg, staging)
        written = [output.final_path(p) for p in paths.values() if p.exists()]
    if rrd_path is not None:
        rrd_path = output.final_path(rrd_path)
        if rrd_path.is_file():  # rerun writes 0600
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(rrd_path, 0o666 & ~umask)
    print_input_warnings(reg)
    summary_table(reg)
    typer.echo(
        f"wrote {', '.join(str(p) for p in written)}"
        + (f", {rrd_path}" if rrd_path is not None else "")
    )
    return 0 if reg.all_registered else 3


def _verification_rows(t, reg) -> None:
    """'verified: N of M' and one row per scan left out, with the reason."""
    ver = reg.verification or {}
    if not ver:
        return
    n_ok = sum(1 for v in ver.values() if v["status"] == "verified")
    n_all = len(reg.all_scan_names)
    partial = "" if n_ok == n_all else " [red](partial result)[/]"
    t.add_row("verified poses", f"verified: {n_ok} of {n_all}{partial}")
    for name, v in ver.items():
        if v["status"] in ("unverified", "undetermined"):
            t.add_row(f"[red]{v['status']}[/]", f"{name}: {v['reason']}")
            if v["degenerate_dof"]:
                t.add_row("", f"  free: {v['degenerate_dof']}")


def summary_table(reg) -> None:
    from rich.console import Console
    from rich.table import Table

    c = reg.solve.certificate if reg.solve is not None else None
    t = Table(title="mvreg register", show_header=False)
    t.add_row("scans", f"{len(reg.all_scan_names)} ({len(reg.T_world_scan)} registered)")
    if reg.unregistered:
        t.add_row("[red]unregistered[/]", ", ".join(reg.unregistered))
    for s in reg.rejected_scans:
        t.add_row("[red]left out[/]", f"{s['scan']}: {s['reason']}")
    if reg.local_frame_offset is not None:
        offset = ", ".join(f"{x:.10g}" for x in reg.local_frame_offset)
        t.add_row(
            "local frame offset",
            f"({offset}) subtracted while registering; outputs in the files' frame",
        )
    _verification_rows(t, reg)
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
        from mvreg.config import load_config
        from mvreg.io.output_folder import OutputFolder

        scans_dir, result_dir = out / "scans", out / "result"
        OutputFolder(result_dir, force=force, inputs=[scans_dir]).check()  # refuse early
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
        code = register_folder(scans_dir, result_dir, load_config(seed=seed), force=force)
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
            "centroids; verified: "
            f"{sum(v['status'] == 'verified' for v in report['verification']['scans'].values())}"
            f" of {len(report['scans'])} scans; global solve certified optimal for the accepted "
            f"pairs: {report['certificate']['certified']}"
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
        est = read_poses_json(poses_path, dim=None)
        tru = read_poses_json(truth, dim=None)
        common = [n for n in est if n in tru]
        if len(common) < 2:
            raise InputError(
                f"{truth}: {len(common)} scan(s) in common with {poses_path}, need at least 2"
            )
        d_est, d_tru = next(iter(est.values())).shape[0], next(iter(tru.values())).shape[0]
        if d_est != d_tru:
            raise InputError(f"{truth}: {d_tru}x{d_tru} poses, {poses_path} has {d_est}x{d_est}")
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
            warn(
                f"{truth}: {len(missing)} scan(s) of the truth have no pose in {poses_path} "
                f"(unregistered): {some(missing)}"
            )

    run_guarded(_run)
