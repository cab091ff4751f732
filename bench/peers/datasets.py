"""Every method on one folder of scans: the bunny and data_synth scans of each mesh.

:func:`run_scan_dataset` returns one row per method (errors vs the truth, overlap
residual, pairwise and global seconds, notes); :func:`run_bunny` and :func:`run_synth`
call it on the Stanford bunny and on synthetic scans of a mesh in one condition.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from bench.common import BUNNY, bunny_truth
from bench.peers.chaining import chain_mvreg_pairs
from bench.peers.gtsam import gtsam_solve
from bench.peers.mvreg_run import global_seconds, rerun_global, run_default
from bench.peers.open3d import run_open3d_fed, run_open3d_own
from bench.peers.settings import CONDITIONS, REFERENCE, ROT_OK_DEG, TR_OK_PCT


def evaluate(T_world: dict, names, scans_by_name, truth, overlap_dist, unit_scale) -> dict:
    """Errors (gauge-free) on the scans a method registered + overlap residual."""
    from mvreg.geometry import transform_points
    from mvreg.metrics import overlap_residual, pose_errors

    got = [n for n in names if n in T_world]
    out = {"registered": len(got), "scans": len(names)}
    if len(got) >= 2:
        e = pose_errors(np.stack([T_world[n] for n in got]), np.stack([truth[n] for n in got]))
        out |= {
            "rot_per_scan": {n: float(x) for n, x in zip(got, e.rotation_deg, strict=True)},
            "rot_med": float(np.median(e.rotation_deg)),
            "rot_max": float(np.max(e.rotation_deg)),
            "tr_med": float(np.median(e.translation)) * unit_scale,
            "tr_max": float(np.max(e.translation)) * unit_scale,
            "within": bool(
                len(got) == len(names)
                and np.max(e.rotation_deg) <= ROT_OK_DEG
                and np.max(e.translation) * unit_scale <= TR_OK_PCT
            ),
        }
        world = [transform_points(T_world[n], scans_by_name[n]) for n in got]
        ov = overlap_residual(world, overlap_dist)
        out |= {
            "overlap_mean": ov["mean"] * unit_scale if ov["mean"] is not None else None,
            "overlap_fraction": ov["overlap_fraction"],
        }
    return out


def run_scan_dataset(
    label, folder, truth, seed, unit_scale, overlap_dist=None, log=print, solvers=True
):
    """Every method on one folder of scans. unit_scale converts data units to the report's
    (1000 for mm; 100 / diagonal for % of the diagonal)."""
    from mvreg.solver import SOLVERS

    rows = []
    reg, cached = run_default(folder, truth, seed)
    tm = reg.timings
    pair_s = tm["preprocess"] + tm["pairwise"]
    scans = reg.scans
    names = [s.name for s in scans]
    pts = {s.name: s.points for s in scans}
    n = len(names)
    if overlap_dist is None:  # register's own cut-off (pipeline._evaluate)
        pre = cached.pre
        spacing = float(np.median([p.noise for p in pre]))
        overlap_dist = max(2.0 * pre[0].fine_voxel_size, 10 * spacing)
    v = reg.voxel_size

    def add(method, T_named, pairwise_s, global_s, note=""):
        r = {"dataset": label, "method": method, "pairwise_s": pairwise_s, "global_s": global_s}
        r |= {"note": note, **evaluate(T_named, names, pts, truth, overlap_dist, unit_scale)}
        rows.append(r)
        log(
            f"  {method:22s} {r['registered']}/{n}  rot max {r.get('rot_max', float('nan')):8.3f}"
            f"  tr max {r.get('tr_max', float('nan')):8.3f}  {pairwise_s:6.1f}+{global_s:6.2f} s"
        )

    cert = reg.solve.certificate.certified if reg.solve is not None else None
    add("mvreg", reg.T_world_scan, pair_s, global_seconds(tm), f"certified={cert}")
    variants = [(s, {"solve.solver": s}) for s in SOLVERS if s != "reg-admm"] if solvers else []
    variants.append(("no-refine", {"refine.rounds": 0}))
    for tag, over in variants:
        try:
            r2 = rerun_global(folder, cached, truth, seed=seed, **over)
            c2 = r2.solve.certificate.certified if r2.solve is not None else None
            add(
                f"mvreg/{tag}",
                r2.T_world_scan,
                pair_s,
                global_seconds(r2.timings),
                f"certified={c2}",
            )
        except Exception as e:  # a solver refusing this input is a result too
            rows.append({"dataset": label, "method": f"mvreg/{tag}", "failed": str(e)[:160]})
            log(f"  mvreg/{tag} failed: {e}")

    # mvreg's accepted pairs (identical edges for Open3D-fed and GTSAM).
    results = cached.results
    rel = {(r.i, r.j): np.asarray(r.T_i_j) for r in results if r.accepted}

    Tt = [np.asarray(truth[k]) for k in names]

    def wrong(i, j, T_i_j):  # an edge more than 2 deg or 2 voxels off the truth
        E = np.linalg.inv(np.linalg.inv(Tt[i]) @ Tt[j]) @ T_i_j
        ang = np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1)))
        return bool(ang > 2.0 or np.linalg.norm(E[:3, 3]) > 2 * v)

    n_wrong = sum(wrong(i, j, T) for (i, j), T in rel.items())
    mvreg_edges = f"{len(rel)} accepted pairs, {n_wrong} wrong"
    rows[0]["note"] += f"; {mvreg_edges}"
    rows[0] |= {"edges_total": len(rel), "edges_wrong": n_wrong}
    kinds = {}
    for r in results:
        if not r.accepted:
            k = next(
                (
                    w
                    for w in ("residual", "feature matching", "free space", "overlap")
                    if w in r.reason
                ),
                "other",
            )
            kinds[k] = kinds.get(k, 0) + 1
            if r.reason.startswith("residual inf"):
                kinds["residual, infinite ratio"] = kinds.get("residual, infinite ratio", 0) + 1
    rows[0]["note"] += "; rejected pairs by reason: " + (
        ", ".join(f"{k} {c}" for k, c in sorted(kinds.items(), key=lambda x: -x[1])) or "none"
    )
    rows[0]["rejected_by_reason"] = kinds

    o3 = run_open3d_own([pts[k] for k in names], v, seed)
    name_T = lambda d: {names[k]: T for k, T in d.items()}  # noqa: E731
    w_odo = sum(wrong(t, s_, T) for s_, t, T, unc in o3["edge_list"] if not unc)
    w_loop = sum(wrong(t, s_, T) for s_, t, T, unc in o3["edge_list"] if unc)
    add(
        "open3d",
        name_T(o3["T"]),
        o3["pairwise_s"],
        o3["global_s"],
        f"{o3['edges']}; wrong: {w_odo} odometry, {w_loop} loop closures",
    )
    rows[-1] |= {
        "odo_total": n - 1,
        "odo_wrong": w_odo,
        "loop_total": sum(1 for e in o3["edge_list"] if e[3]),
        "loop_wrong": w_loop,
    }
    add(
        "open3d/all-uncertain",
        name_T(o3["T_all_uncertain"]),
        o3["pairwise_s"],
        o3["global_s_all_uncertain"],
        "diagnostic: Open3D's own edges, odometry edges also uncertain (prunable)",
    )
    fed = None
    if rel:
        fed = run_open3d_fed(n, rel, o3["prep"], v, pair_s)
        add("open3d/mvreg-pairs", name_T(fed["T"]), fed["pairwise_s"], fed["global_s"], mvreg_edges)
    else:
        rows.append(
            {"dataset": label, "method": "open3d/mvreg-pairs", "failed": "mvreg accepted no pairs"}
        )

    try:
        if fed is None:
            raise ValueError("mvreg accepted no pairs")
        g = gtsam_solve(n, rel, fed["cov"])
        add(
            "gtsam",
            name_T(g["T"]),
            pair_s,
            g["rotation_s"] + g["translation_s"],
            f"Shonan {g['rotation_s']:.2f} s + poses {g['translation_s']:.2f} s, "
            f"Shonan certified={g['certified']} (min eig {g['min_eig']:.1e})",
        )
    except Exception as e:
        rows.append({"dataset": label, "method": "gtsam", "failed": str(e)[:160]})
        log(f"  gtsam failed: {e}")

    # Chaining in scan order.
    chain, secs = chain_mvreg_pairs(cached.pre, results, reg.config.align, seed, reg.scales)
    secs += tm["preprocess"]
    bad = sum(wrong(k, k + 1, np.linalg.inv(chain[k]) @ chain[k + 1]) for k in range(n - 1))
    add("chain/mvreg-pairs", name_T(chain), secs, 0.0, f"{bad} of {n - 1} links wrong")
    rows[-1] |= {"links_wrong": bad, "links": n - 1}
    bad = sum(wrong(t, s_, T) for s_, t, T, unc in o3["edge_list"] if not unc)
    add(
        "chain/open3d-pairs",
        name_T(o3["chain_T"]),
        o3["chain_pairwise_s"],
        0.0,
        f"{bad} of {n - 1} links wrong",
    )
    rows[-1] |= {"links_wrong": bad, "links": n - 1}
    add(
        REFERENCE,
        {k: np.asarray(truth[k]) for k in names},
        0.0,
        0.0,
        "overlap residual of the truth",
    )
    return rows


def run_bunny(seed: int, log=print) -> list[dict]:
    folder = BUNNY
    if not (folder / "bun.conf").exists():
        sys.exit(f"{folder}: missing (../shared/data must be beside the project)")
    return run_scan_dataset("bunny", folder, bunny_truth(folder), seed, 1000.0, 0.5e-3, log)


def run_synth(mesh: Path, cond: str, seed: int, tmp: Path, log=print, solvers=True) -> list[dict]:
    from data_synth import synthesize_scans

    d = tmp / f"{mesh.stem}_{cond.split()[0]}_{seed}"
    s = synthesize_scans(
        mesh, d, views=12, seed=seed, random_frames=True, force=True, **CONDITIONS[cond]
    )
    rows = run_scan_dataset(
        f"{mesh.stem} / {cond} / seed {seed}",
        d,
        s.T_world_scan,
        seed,
        100.0 / s.object_diagonal,
        None,
        log,
        solvers,
    )
    for r in rows:
        r |= {"mesh": mesh.stem, "condition": cond, "seed": seed}
    return rows
