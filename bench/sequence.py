"""Benchmark of `register_sequence` (ordered LiDAR scans) against the target of issue 4.

Target: on a closed-loop synthetic sequence of 200 scans, the end-to-start position error
at least 5x smaller than KISS-ICP odometry alone, and the rotation error below 0.5 degrees
for every scan.

For each seed, data_synth's sequence mode drives a 32-beam LiDAR once around a closed
loop (an ellipse of 15 x 10 m through a scene of objects, box buildings and a ground
plane, range noise 0.2% of the object size); the scans are registered with default
settings; the KISS-ICP poses (odometry alone) and the final poses are compared with the
ground truth. On the first seed the global stage is also run with mutual-nearest-
neighbour tracks and `register`'s multiview ICP (`sequence.correspondences="nearest"`),
to show why the sequence mode builds its tracks from the pairs' poses.

Writes docs/benchmarks/sequence.md and sequence.png.

    python scripts/bench_sequence.py             # 3 seeds x 200 scans, + the ablation
    python scripts/bench_sequence.py --quick     # 1 seed x 100 scans, no ablation
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import ROOT, machine


def anchored(T: np.ndarray) -> np.ndarray:
    """(M, 4, 4) poses seen from the first one."""
    from mvreg.geometry import invert_transform

    return np.einsum("ij,mjk->mik", invert_transform(T[0]), T)


def run(seed: int, frames: int, points: int, tmp: Path, correspondences: str = "pose") -> dict:
    from data_synth import synthesize_sequence
    from mvreg.geometry import rotation_angle_deg
    from mvreg.metrics import pose_errors
    from mvreg.sequence import register_sequence

    folder = tmp / f"seq_{seed}_{frames}_{points}"
    t0 = time.perf_counter()
    t_synth = None  # reused from an earlier run (--data)
    if not folder.exists():
        synthesize_sequence(None, folder, frames=frames, points_per_scan=points, seed=seed)
        t_synth = time.perf_counter() - t0
    t0 = time.perf_counter()
    reg = register_sequence(folder, **{"sequence.correspondences": correspondences})
    wall = time.perf_counter() - t0
    from mvreg.io.poses import read_poses_json

    truth = read_poses_json(folder / "ground_truth.json")
    names = reg.scan_names
    G = np.stack([truth[n] for n in names])
    K = np.stack([reg.T_odom_scan[n] for n in names])
    ok = [n in reg.T_world_scan for n in names]
    M = np.stack([reg.T_world_scan.get(n, np.full((4, 4), np.nan)) for n in names])
    Ga, Ka = anchored(G), anchored(K)
    Ma = anchored(M) if ok[0] else np.full_like(M, np.nan)

    def anchored_errors(A):
        pos = np.linalg.norm(A[:, :3, 3] - Ga[:, :3, 3], axis=1)
        rot = rotation_angle_deg(np.einsum("mji,mjk->mik", Ga[:, :3, :3], A[:, :3, :3]))
        return pos, rot

    kiss_pos, kiss_rot = anchored_errors(Ka)
    mv_pos, mv_rot = anchored_errors(Ma)
    d = reg.sequence["drift"]
    e = reg.truth_errors
    kiss_err = pose_errors(K, G)
    step_true = np.linalg.norm(np.diff(G[:, :3, 3], axis=0), axis=1)
    step_kiss = np.linalg.norm(np.diff(K[:, :3, 3], axis=0), axis=1)
    return {
        "seed": seed,
        "frames": frames,
        "points": points,
        "correspondences": correspondences,
        "scans": len(names),
        "registered": len(reg.T_world_scan),
        "path": d["truth_path_length"],
        "kiss_end": d["odometry_end_to_start_vs_truth"],
        "kiss_end_rot": d["odometry_end_to_start_rotation_deg_vs_truth"],
        "mv_end": d["global_end_to_start_vs_truth"],
        "mv_end_rot": d["global_end_to_start_rotation_deg_vs_truth"],
        "ratio": d["reduction_vs_truth"],
        "mv_rot_max": e["rotation_deg_max"],
        "mv_rot_med": e["rotation_deg_median"],
        "mv_tr_max": e["translation_max"],
        "mv_tr_med": e["translation_median"],
        "kiss_rot_max": float(kiss_err.rotation_deg.max()),
        "kiss_stalled": int(np.sum(step_kiss < 0.5 * step_true)),
        "kiss_tr_max": float(kiss_err.translation.max()),
        "mv_anchored_pos_max": float(np.nanmax(mv_pos)),
        "kiss_anchored_pos_max": float(np.max(kiss_pos)),
        "loops": reg.sequence["loop_closures"],
        "pairs": reg.sequence["pairs_by_kind"],
        "certified": bool(reg.solve is not None and reg.solve.certified),
        "timings": reg.timings,
        "wall": wall,
        "synth": t_synth,
        "curves": {
            "truth_xy": Ga[:, :2, 3],
            "kiss_xy": Ka[:, :2, 3],
            "mv_xy": Ma[:, :2, 3],
            "kiss_pos": kiss_pos,
            "mv_pos": mv_pos,
            "kiss_rot": np.asarray(kiss_err.rotation_deg),
            "mv_rot": np.asarray(e["rotation_deg"]),
        },
    }


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--quick", action="store_true", help="one seed, 100 scans, no ablation")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--points", type=int, default=10_000, help="points per scan (about)")
    ap.add_argument("--no-ablation", action="store_true")
    ap.add_argument("--data", type=Path, help="keep the synthetic sequences here")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks")
    a = ap.parse_args(argv)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    if a.quick:
        a.seeds, a.frames, a.no_ablation = 1, 100, True
    t_all = time.perf_counter()
    rows, ablation = [], None
    with tempfile.TemporaryDirectory() as tmp_dir:
        tmp = a.data if a.data is not None else Path(tmp_dir)
        tmp.mkdir(parents=True, exist_ok=True)
        for seed in range(a.seeds):
            r = run(seed, a.frames, a.points, tmp)
            print(
                f"seed {seed}: KISS-ICP end-to-start {r['kiss_end']:.3f} m, mvreg "
                f"{r['mv_end']:.4f} m ({r['ratio']:.0f}x), rotation max {r['mv_rot_max']:.3f} deg, "
                f"{r['wall']:.0f} s",
                file=sys.stderr,
            )
            rows.append(r)
        if not a.no_ablation:
            ablation = run(0, a.frames, a.points, tmp, correspondences="nearest")
            print(
                f"nearest-neighbour tracks: rotation max {ablation['mv_rot_max']:.3f} deg",
                file=sys.stderr,
            )
    write_report(a, rows, ablation, time.perf_counter() - t_all)


def write_report(a, rows, ablation, total) -> None:
    a.out.mkdir(parents=True, exist_ok=True)
    cmd = (
        "python scripts/bench_sequence.py"
        + (
            " --quick"
            if a.quick
            else f" --seeds {a.seeds} --frames {a.frames} --points {a.points}"
            + (" --no-ablation" if a.no_ablation else "")
        )
        + (f" --data {a.data}" if a.data is not None else "")
    )
    ok = lambda c: "yes" if c else "**no**"  # noqa: E731
    first = rows[0]
    L = [
        "# `register_sequence`: ordered LiDAR scans, KISS-ICP odometry + loop closures + REG-ADMM",
        "",
        f"- Command: `{cmd}` ({datetime.date.today().isoformat()}); total {total:.0f} s",
        f"- Machine: {machine()}; `OPENBLAS_NUM_THREADS=1`, KISS-ICP on 1 thread",
        f"- Data: `data_synth.synthesize_sequence(None, dir, frames={a.frames}, "
        f"points_per_scan={a.points}, seed=s)`: a 32-beam LiDAR (FOV -25..15 deg, 60 m range) "
        "driven once around a closed 15 x 10 m ellipse (path about 79 m) through 12 objects and "
        "10 box buildings on a ground plane, range noise 0.2% of the object size (8 mm), "
        "scans in the sensor frame, `timestamps.txt` at 10 Hz.",
        "- Settings: defaults (`mvreg.sequence.register_sequence(folder)`), no per-dataset tuning.",
        "- End-to-start error: position of the last scan seen from the first, "
        "`inv(T_first) T_last`, against the same from the ground truth (metres; the scene is "
        "in metres). Rotation error per scan: after the best global rotation "
        "(`mvreg.metrics.pose_errors`).",
        "",
        "## Target",
        "",
        "| seed | scans registered | KISS-ICP end-to-start (m) | mvreg end-to-start (m) | ratio (target >= 5) | met | rotation error max, every scan (deg; target < 0.5) | met |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        L.append(
            f"| {r['seed']} | {r['registered']} / {r['scans']} | {r['kiss_end']:.3f} "
            f"({100 * r['kiss_end'] / r['path']:.2f}% of path) | {r['mv_end']:.4f} | "
            f"{r['ratio']:.0f}x | {ok(r['ratio'] >= 5)} | {r['mv_rot_max']:.3f} | "
            f"{ok(r['mv_rot_max'] < 0.5 and r['registered'] == r['scans'])} |"
        )
    L += [
        "",
        "## Details",
        "",
        "| seed | KISS-ICP steps shorter than half the true step | KISS-ICP rotation max (deg) | KISS-ICP position max (m, gauge-aligned) | mvreg rotation median / max (deg) | mvreg position median / max (m, gauge-aligned) | end-to-start rotation KISS-ICP / mvreg (deg) | loop closures accepted / candidates | sequential pairs accepted / tried (feature RANSAC) | certified | time (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        sp = r["pairs"]["sequential"]
        L.append(
            f"| {r['seed']} | {r['kiss_stalled']} / {r['scans'] - 1} | {r['kiss_rot_max']:.3f} | {r['kiss_tr_max']:.3f} | "
            f"{r['mv_rot_med']:.3f} / {r['mv_rot_max']:.3f} | {r['mv_tr_med']:.4f} / {r['mv_tr_max']:.4f} | "
            f"{r['kiss_end_rot']:.3f} / {r['mv_end_rot']:.4f} | {r['loops']['accepted']} / {r['loops']['candidates']} | "
            f"{sp['accepted']} / {sp['tried']} ({sp['feature_ransac']}) | {r['certified']} | {r['wall']:.0f} |"
        )
    L += ["", "Stage times (s), per seed:", ""]
    for r in rows:
        L.append(
            f"- seed {r['seed']}: "
            + ", ".join(f"{k} {v:.1f}" for k, v in r["timings"].items())
            + (
                " (data reused from --data)"
                if r["synth"] is None
                else f" (data synthesis {r['synth']:.1f}, not included)"
            )
        )
    if ablation is not None:
        b = ablation
        L += [
            "",
            "## Why tracks from the pairs' poses (seed 0, same pairs)",
            "",
            "`register` links mutual nearest neighbours into tracks and refines by multiview ICP. "
            "Two sparse LiDAR scans never sample the same physical points (their rings cut the "
            "ground along different circles), so those links pull the scans by the sampling "
            "pattern. The sequence mode instead turns each verified pair's point-to-plane ICP "
            "alignment into point correspondences (`mvreg.sequence.pose_tracks`). Both end "
            "with the joint point-to-plane ICP over the pairs they kept.",
            "",
            "| tracks | rotation median / max (deg) | position median / max (m) | end-to-start (m) | time (s) |",
            "|---|---|---|---|---|",
            f"| pose tracks (default) | {first['mv_rot_med']:.3f} / {first['mv_rot_max']:.3f} | "
            f"{first['mv_tr_med']:.4f} / {first['mv_tr_max']:.4f} | {first['mv_end']:.4f} | {first['wall']:.0f} |",
            f"| nearest neighbours + multiview ICP | {b['mv_rot_med']:.3f} / {b['mv_rot_max']:.3f} | "
            f"{b['mv_tr_med']:.4f} / {b['mv_tr_max']:.4f} | {b['mv_end']:.4f} | {b['wall']:.0f} |",
        ]
    L += [
        "",
        "## Notes",
        "",
        "- KISS-ICP runs with settings scaled to the data (voxel = max range / 100, its own "
        "default ratio), deskewing off (the synthetic scans are instantaneous). It starts from "
        "zero velocity; the column 'steps shorter than half the true step' counts the scans "
        "where it lagged or stalled (the ground rings look alike from one scan to the next). "
        "On sparser scans (about 4,000 points, the test suite's sequence) it stalls for the "
        "whole loop; the pairs verified by ICP from other guesses recover the motion there.",
        "- Right panel (seed 0): mvreg's rotation error stays in a narrow band along the whole "
        "loop instead of growing with the distance travelled. Before the joint point-to-plane "
        "ICP (`mvreg.joint_icp`) ended the global stage, that band was about 3x higher (max "
        "0.196 / 0.144 / 0.142 deg for seeds 0-2 in the 2026-11-22 run of this command): the "
        "pose tracks carried each pair's alignment error in the directions its overlap leaves "
        "free.",
        "- The end-to-start error after the global solve is small partly because the first and "
        "last scans are joined directly by verified loop-closure pairs; the per-scan columns "
        "show the error along the whole loop.",
        "- Times are wall times on a shared 2-core machine (upper bounds). KISS-ICP's own time "
        "is the `odometry` stage.",
        "",
        "![trajectories and errors](sequence.png)",
    ]
    (a.out / "sequence.md").write_text("\n".join(L) + "\n")
    plot(a.out / "sequence.png", first)
    print((a.out / "sequence.md").read_text())


def plot(path: Path, r: dict) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    c = r["curves"]
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.5))
    ax[0].plot(*c["truth_xy"].T, "k-", lw=2, label="ground truth")
    ax[0].plot(*c["kiss_xy"].T, "-", color="tab:orange", label="KISS-ICP alone")
    ax[0].plot(*c["mv_xy"].T, "--", color="tab:blue", label="mvreg (global)")
    ax[0].plot(*c["truth_xy"][0], "ko")
    ax[0].set_aspect("equal")
    ax[0].set_xlabel("x from the first scan (m)")
    ax[0].set_ylabel("y (m)")
    ax[0].set_title(f"seed {r['seed']}: trajectories, first scan at the origin")
    ax[0].legend()
    k = np.arange(len(c["kiss_pos"]))
    ax[1].semilogy(k, np.maximum(c["kiss_pos"], 1e-5), color="tab:orange", label="KISS-ICP alone")
    ax[1].semilogy(k, np.maximum(c["mv_pos"], 1e-5), color="tab:blue", label="mvreg")
    ax[1].set_xlabel("scan")
    ax[1].set_ylabel("position error seen from the first scan (m)")
    ax[1].set_title("drift along the loop")
    ax[1].legend()
    ax[2].plot(k, c["kiss_rot"], color="tab:orange", label="KISS-ICP alone")
    ax[2].plot(k[: len(c["mv_rot"])], c["mv_rot"], color="tab:blue", label="mvreg")
    ax[2].axhline(0.5, color="grey", ls="--", label="target 0.5 deg")
    ax[2].set_yscale("log")
    ax[2].set_xlabel("scan")
    ax[2].set_ylabel("rotation error (deg, best global rotation)")
    ax[2].set_title("rotation error per scan")
    ax[2].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
