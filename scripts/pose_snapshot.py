"""Pose snapshot for refactoring: the poses and certificates of a fixed set of runs, to
compare bit for bit before and after a change that must not change behaviour.

    python scripts/pose_snapshot.py before.npz [bunny,builtin,synth,synth0,seq]
    python scripts/pose_snapshot.py --compare before.npz after.npz

The inputs are synthesized once into ``$MVREG_SNAPSHOT_DATA`` (default
/tmp/mvreg_snapshot_data) so both sides read the same files: the real bunny scans, the
demo's builtin set (12 views, 0.2% noise, seed 0), the five original shared meshes with
seeds 0 and 1 (``synth``) or 0 (``synth0``), clean, 10% outliers and two injected wrong
pairs, and a 60-scan LiDAR sequence. Run it with PYTHONPATH pointing at the checkout to
measure (a git worktree of the commit before the change, then the working tree).
"""

import json
import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
from pathlib import Path

import numpy as np

DATA = Path(os.environ.get("MVREG_SNAPSHOT_DATA", "/tmp/mvreg_snapshot_data"))
SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
MESHES = ["stanford-bunny", "spot", "fandisk", "cow", "teapot"]


def make_data():
    from data_synth import synthesize_scans, synthesize_sequence

    DATA.mkdir(exist_ok=True)
    if not (DATA / "builtin0").exists():
        synthesize_scans(
            "builtin", DATA / "builtin0", views=12, noise=0.002, seed=0, random_frames=True
        )
    for m in MESHES:
        for seed in (0, 1):
            for cond in ("clean", "outliers"):
                d = DATA / f"{m}_{seed}_{cond}"
                if not d.exists():
                    synthesize_scans(
                        SHARED / "meshes" / f"{m}.obj",
                        d,
                        views=12,
                        noise=0.002,
                        outliers=0.1 if cond == "outliers" else 0.0,
                        seed=seed,
                        random_frames=True,
                    )
    if not (DATA / "seq0").exists():
        synthesize_sequence(None, DATA / "seq0", frames=60, points_per_scan=5000, seed=0)


def reg_fn():
    from mvreg import register

    return register


def compare(a_path, b_path) -> int:
    a, b = np.load(a_path), np.load(b_path)
    ka, kb = set(a.files), set(b.files)
    diff = 0
    for k in sorted(ka & kb):
        x, y = a[k], b[k]
        same = x.shape == y.shape and np.array_equal(x, y, equal_nan=x.dtype.kind in "fc")
        if not same:
            diff += 1
            print("DIFF", k)
    print(
        f"{len(ka & kb)} common keys, {diff} differ; only in the first: {len(ka - kb)}, "
        f"only in the second: {len(kb - ka)}"
    )
    return 1 if diff else 0


def main():
    if sys.argv[1] == "--compare":
        sys.exit(compare(sys.argv[2], sys.argv[3]))
    out = sys.argv[1]
    only = sys.argv[2].split(",") if len(sys.argv) > 2 else ["bunny", "builtin", "synth", "seq"]
    make_data()
    register = reg_fn()
    from mvreg.io.poses import read_poses_json
    from mvreg.testing import wrong_pair_injector

    res = {}
    times = {}

    def put(key, reg):
        for n, T in reg.T_world_scan.items():
            res[f"{key}/{n}"] = np.asarray(T)
        res[f"{key}/__unregistered"] = np.array(sorted(reg.unregistered), dtype=object).astype(str)
        c = reg.solve.certificate if reg.solve is not None else None
        res[f"{key}/__cert"] = np.array(
            [c.min_eigenvalue if c else np.nan, float(c.certified) if c else np.nan]
        )

    if "bunny" in only:
        t = time.perf_counter()
        reg = register(SHARED / "stanford_bunny_scans")
        times["bunny"] = time.perf_counter() - t
        put("bunny", reg)
    if "builtin" in only:
        t = time.perf_counter()
        reg = register(DATA / "builtin0", seed=0)
        times["builtin"] = time.perf_counter() - t
        put("builtin", reg)
    if "synth" in only or "synth0" in only:
        for m in MESHES:
            for seed in (0, 1) if "synth" in only else (0,):
                for cond in ("clean", "outliers", "wrong"):
                    d = DATA / f"{m}_{seed}_{'outliers' if cond == 'outliers' else 'clean'}"
                    hook = None
                    if cond == "wrong":
                        hook = wrong_pair_injector(
                            read_poses_json(d / "ground_truth.json"), count=2, seed=seed
                        )
                    t = time.perf_counter()
                    reg = register(d, pair_hook=hook, seed=seed)
                    times[d.name + cond] = time.perf_counter() - t
                    put(f"{m}_{seed}_{cond}", reg)
                    print(
                        m,
                        seed,
                        cond,
                        f"{times[d.name + cond]:.1f}s",
                        reg.truth_errors["rotation_deg_max"] if reg.truth_errors else None,
                        flush=True,
                    )
    if "seq" in only:
        from mvreg.sequence import register_sequence

        t = time.perf_counter()
        reg = register_sequence(DATA / "seq0")
        times["seq"] = time.perf_counter() - t
        put("seq", reg)
    np.savez(out, **res)
    print(json.dumps(times, indent=0))


if __name__ == "__main__":
    main()
