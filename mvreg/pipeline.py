"""register(): a folder of scans in, globally aligned poses out. Reads as its stages:

load -> preprocess -> candidate pairs -> pairwise alignment (rotation search for scans it
leaves unconnected) -> tracks -> global solve
-> robust re-weighting -> multiview refinement -> evaluation.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mvreg.config import RegisterConfig, load_config
from mvreg.errors import InputError
from mvreg.geometry import transform_points
from mvreg.io.loaders import Scan, list_scan_files, load_scan
from mvreg.joint_icp import joint_icp
from mvreg.metrics import overlap_residual, pose_errors
from mvreg.pairwise import (
    PairResult,
    align_pairs,
    build_tracks,
    candidate_pairs,
    derive_voxel_size,
    preprocess_all,
)
from mvreg.pairwise.consistency import inconsistent_pairs
from mvreg.pairwise.search import connect_unconnected
from mvreg.refine import (
    GlobalSolution,
    pair_disagreements,
    prepare_dense_levels,
    refine_rounds,
    robust_rounds,
    solve_tracks,
)
from mvreg.verification import NOTE as VERIFICATION_NOTE
from mvreg.verification import ScanVerification, verify_and_resolve
from mvreg.viz import NullRecorder


class _NoProgress:
    def stage(self, name: str, total: int | None = None) -> None: ...
    def advance(self, n: int = 1) -> None: ...
    def done(self) -> None: ...


@dataclass
class Registration:
    """The result of ``register``.

    T_world_scan: {scan name: (4, 4) world_from_scan} for every registered scan; the world
    frame is the first registered scan; every pose in it is verified
    (:mod:`mvreg.verification`). ``unregistered`` lists the scans that could not be
    connected to the rest (never given a made-up pose); ``unverified`` and
    ``undetermined`` those left out because no independent evidence confirms their pose or
    a degree of freedom of it is not fixed by the data (``verification`` says why).
    """

    scan_names: list[str]
    T_world_scan: dict[str, np.ndarray]
    unregistered: list[str]
    solve: object
    pairs: list[dict]
    config: RegisterConfig
    voxel_size: float
    timings: dict
    robust_log: list[dict] = field(default_factory=list)
    refine_log: list[dict] = field(default_factory=list)
    joint_icp: dict | None = None  # the joint point-to-plane ICP after the rounds
    overlap: dict | None = None
    truth_errors: dict | None = None
    scans: list[Scan] = field(default_factory=list, repr=False)
    source: str | None = None
    unverified: list[str] = field(default_factory=list)  # left out: pose not confirmed
    undetermined: list[str] = field(default_factory=list)  # left out: a free DOF
    verification: dict = field(default_factory=dict)  # {scan: ScanVerification.to_dict()}

    @property
    def all_registered(self) -> bool:
        """Every scan placed and its pose verified."""
        return not (self.unregistered or self.unverified or self.undetermined)

    def __repr__(self) -> str:
        c = self.solve.certificate if self.solve is not None else None
        return (
            f"Registration(scans={len(self.scan_names)}, registered={len(self.T_world_scan)}, "
            f"unregistered={self.unregistered}, certified={c.certified if c else None}, "
            f"time={self.timings.get('total', float('nan')):.2f}s)"
        )

    def report(self) -> dict:
        """The content of report.json."""
        s = self.solve
        return {
            "format": "mvreg.report/1",
            "source": self.source,
            "config": self.config.model_dump(mode="json"),
            "voxel_size": self.voxel_size,
            "scans": self.scan_names,
            "registered": list(self.T_world_scan),
            "unregistered": self.unregistered,
            "unverified": self.unverified,
            "undetermined": self.undetermined,
            "verification": {"scans": self.verification, "note": VERIFICATION_NOTE},
            "timings_s": self.timings,
            "pairs": self.pairs,
            "bad_pairs": [p for p in self.pairs if p["accepted"] and p["final_weight"] == 0.0],
            "solver": None if s is None else s.to_dict(),
            "certificate": None if s is None or s.certificate is None else s.certificate.to_dict(),
            "robust_rounds": self.robust_log,
            "refine_rounds": self.refine_log,
            "joint_icp": self.joint_icp,
            "overlap_residual": self.overlap,
            "ground_truth_errors": self.truth_errors,
        }


def register(
    source: str | Path | Sequence[np.ndarray],
    config: RegisterConfig | None = None,
    *,
    names: Sequence[str] | None = None,
    recorder=None,
    progress=None,
    truth: dict[str, np.ndarray] | None = None,
    pair_hook=None,
    **overrides,
) -> Registration:
    """Register a folder of scans (or a list of (N, 3) arrays) into one frame.

    Args:
        source: folder of scan files, or point arrays in their own frames.
        config: a RegisterConfig; else defaults with ``overrides`` (dotted keys, e.g.
            ``**{"solve.solver": "gpm"}``, or plain ``seed=1``).
        names: names of the arrays when ``source`` is a list.
        recorder: a mvreg.viz Recorder (default: none).
        progress: an object with stage(name, total) / advance(n) / done() (CLI: rich bars).
        truth: {name: 4x4 T_world_scan} to evaluate against; by default read from
            ``ground_truth.json`` in the folder. Used only to evaluate, never to solve.
        pair_hook: optional ``f(pre, results) -> results`` applied after pairwise
            alignment (benchmarks and tests use it to inject wrong pairs).
    """
    cfg = config if config is not None else load_config(**overrides)
    rec = recorder if recorder is not None else NullRecorder()
    prog = progress if progress is not None else _NoProgress()
    timings: dict = {}
    t_start = time.perf_counter()

    def timed(name):
        timings[name] = time.perf_counter() - timed.t
        timed.t = time.perf_counter()

    timed.t = t_start

    scans, source_str, truth = load_source(source, names, cfg, truth, prog)
    timed("load")
    rec.log_config(cfg.model_dump(mode="json"))
    rec.log_raw_scans([s.name for s in scans], [s.points for s in scans])

    voxel = derive_voxel_size(scans, cfg.preprocess)
    prog.stage("preprocess", len(scans))
    pre = preprocess_all(
        scans, voxel, cfg.preprocess, cfg.workers, progress=lambda _p: prog.advance()
    )
    timed("preprocess")

    pairs = candidate_pairs(pre, cfg.pairs)
    prog.stage("pairs", len(pairs))
    results = align_pairs(
        pre, pairs, cfg.align, cfg.seed, progress=lambda _r: prog.advance(), workers=cfg.workers
    )
    results = connect_unconnected(pre, results, cfg.align, cfg.search, workers=cfg.workers)
    if pair_hook is not None:
        results = pair_hook(pre, results)
    timed("pairwise")

    prog.stage("global solve")
    step = [0]

    def on_iteration(r):
        step[0] += 1
        rec.log_solver_iteration(step[0], r.objective, r.primal_residual, r.dual_residual, r.rho)

    dense_levels = prepare_dense_levels(scans, pre, cfg)  # in the background meanwhile

    def global_stage(res) -> _GlobalStage:
        """Tracks -> global solve -> robust -> refinement -> joint ICP -> final check."""
        w0, rlog = _cycle_check(pre, res, cfg)
        tracks = build_tracks(pre, res, cfg.tracks, pair_weights=w0, workers=cfg.workers)
        st = _GlobalStage(tracks, None, np.zeros(len(tracks.pairs)), rlog)
        if tracks.problem is None:
            return st
        sol = solve_tracks(tracks, cfg, callback=on_iteration)
        timed("tracks_and_solve")
        prog.stage("robust re-weighting")
        sol, weights, log = robust_rounds(
            tracks, sol, voxel, cfg, callback=on_iteration, weights=w0
        )
        st.robust_log += log
        timed("robust")
        prog.stage("refinement", cfg.refine.rounds)
        sol, st.refine_log = refine_rounds(
            pre, sol, cfg, callback=on_iteration, scans=scans, dense_levels=dense_levels
        )
        if cfg.refine.rounds:
            levels = dense_levels.result() if dense_levels is not None else None
            sol, st.joint_log = joint_icp(pre, sol, cfg, levels=levels)
        st.sol = sol
        st.weights = _final_check(pre, res, tracks, weights, sol, voxel, cfg, st.robust_log)
        timed("refine")
        return st

    stage = global_stage(results)
    # Verification: scans not confirmed by independent evidence leave; the rest is solved
    # again without their pairs (mvreg.verification).
    t_verify = time.perf_counter()
    stage, verification, dropped = verify_and_resolve(
        pre, results, stage, global_stage, voxel, cfg.align
    )
    timed("verify")  # after the last re-solve (whose stages overwrite their timings)
    timings["verify_with_resolves"] = time.perf_counter() - t_verify
    prog.done()
    tracks, weights, robust_log = stage.tracks, stage.weights, stage.robust_log
    refine_log, joint_log, sol = stage.refine_log, stage.joint_log, stage.sol

    names_all = [s.name for s in scans]
    T = {names_all[i]: sol.T_world_scan[i] for i in sorted(stage.T_world_scan) if i not in dropped}
    unregistered = [n for k, n in enumerate(names_all) if n not in T and k not in dropped]
    status = {names_all[k]: v for k, v in verification.items()}
    for n in unregistered:
        status[n] = ScanVerification(
            "unregistered", "not connected to the others by accepted pairs"
        )
    pair_table = _pair_table(results, tracks, weights)
    reg = Registration(
        scan_names=names_all,
        T_world_scan=T,
        unregistered=unregistered,
        solve=None if sol is None else sol.result,
        pairs=pair_table,
        config=cfg,
        voxel_size=voxel,
        timings=timings,
        robust_log=robust_log,
        refine_log=refine_log,
        joint_icp=joint_log,
        scans=scans,
        source=source_str,
        unverified=[n for n in names_all if status.get(n) and status[n].status == "unverified"],
        undetermined=[n for n in names_all if status.get(n) and status[n].status == "undetermined"],
        verification={n: status[n].to_dict() for n in names_all if n in status},
    )
    _evaluate(reg, pre, truth)
    timed("evaluate")
    timings["total"] = time.perf_counter() - t_start
    if T:
        idx = [names_all.index(n) for n in T]
        rec.log_aligned(list(T), [scans[i].points for i in idx], list(T.values()))
        if cfg.output.record_pair_correspondences and rec.enabled:
            _record_pairs(rec, sol, names_all)
    return reg


@dataclass
class _GlobalStage:
    """What one run of the global stage produced (re-run by the verification)."""

    tracks: object
    sol: GlobalSolution | None
    weights: np.ndarray
    robust_log: list[dict]
    refine_log: list[dict] = field(default_factory=list)
    joint_log: dict | None = None

    @property
    def T_world_scan(self) -> dict[int, np.ndarray]:
        return {} if self.sol is None else self.sol.T_world_scan

    @property
    def pair_weight(self) -> dict[tuple[int, int], float]:
        return {
            (int(i), int(j)): float(w)
            for (i, j), w in zip(self.tracks.pairs, self.weights, strict=True)
        }


def _cycle_check(pre, results, cfg) -> tuple[np.ndarray, list[dict]]:
    """Initial weights of the accepted pairs: 0 for those the cycle check sets aside."""
    accepted = [k for k, r in enumerate(results) if r.accepted]
    w0 = np.ones(len(accepted))
    if cfg.robust.cycle_check_voxels is None:
        return w0, []
    out = inconsistent_pairs(pre, results, cfg.robust.cycle_check_voxels, align_cfg=cfg.align)
    position = {k: n for n, k in enumerate(accepted)}
    for k, _ in out:
        w0[position[k]] = 0.0
    log = {
        "cycle_check": True,
        "limit_voxels": cfg.robust.cycle_check_voxels,
        "pairs_zeroed": [{"scans": list(results[k].names), **info} for k, info in out],
    }
    return w0, [log]


def _final_check(pre, results, tracks, weights, sol, voxel, cfg, robust_log) -> np.ndarray:
    """Zero the weight of accepted pairs whose own pose disagrees with the final poses by
    more than ``cfg.robust.final_disagreement_voxels`` (logged in ``robust_log``)."""
    limit = cfg.robust.final_disagreement_voxels
    if limit is None or not cfg.refine.rounds:
        return weights
    dis = pair_disagreements(pre, results, sol.T_world_scan, voxel)
    weights = np.array(weights, dtype=np.float64)
    index = {(int(i), int(j)): p for p, (i, j) in enumerate(tracks.pairs)}
    zeroed = []
    for (i, j), d in dis.items():
        p = index.get((i, j))
        if p is not None and weights[p] > 0 and d > limit * voxel:
            weights[p] = 0.0
            zeroed.append({"scans": [pre[i].name, pre[j].name], "voxels": d / voxel})
    robust_log.append({"final_check": True, "limit_voxels": limit, "pairs_zeroed": zeroed})
    return weights


def _record_pairs(rec, sol: GlobalSolution, names: list[str]) -> None:
    """Each pair's linked points of the final tracks, in the world frame."""
    tr = sol.tracks
    if len(tr.link_obs) == 0:
        return
    a, b = tr.link_obs[:, 0], tr.link_obs[:, 1]
    for p, (i, j) in enumerate(tr.pairs):
        if int(i) not in sol.T_world_scan or int(j) not in sol.T_world_scan:
            continue
        sel = tr.link_pair == p
        if not np.any(sel):
            continue
        oa, ob = a[sel], b[sel]
        # A link may be stored either way round: put scan i's end first.
        swap = tr.obs_scan[oa] != i
        oa, ob = np.where(swap, ob, oa), np.where(swap, oa, ob)
        pa = transform_points(sol.T_world_scan[int(i)], tr.coords[oa])
        pb = transform_points(sol.T_world_scan[int(j)], tr.coords[ob])
        w = float(tr.pair_weights[p]) if len(tr.pair_weights) > p else None
        rec.log_pair_correspondences(names[int(i)], names[int(j)], pa, pb, w)


def load_source(source, names, cfg, truth, prog, what: str = "registration"):
    """Scans from a folder or from (N, 3) arrays, checked; the source as text; the truth
    (read from ``ground_truth.json`` in the folder when not given)."""
    if isinstance(source, (str, Path)):
        folder = Path(source)
        if not folder.is_dir():
            raise InputError(f"{folder}: not a folder of scans")
        files = list_scan_files(folder)
        if not files:
            raise InputError(f"{folder}: no scan files found")
        prog.stage("load", len(files))
        scans = []
        for f in files:
            scans.append(load_scan(f, min_points=cfg.min_points))
            prog.advance()
        if truth is None and (folder / "ground_truth.json").exists():
            from mvreg.io.poses import read_poses_json

            truth = read_poses_json(folder / "ground_truth.json")
        src = str(folder)
    else:
        arrays = list(source)
        names = list(names) if names is not None else [f"scan_{i:03d}" for i in range(len(arrays))]
        if len(names) != len(arrays):
            raise InputError(f"{len(names)} names for {len(arrays)} point arrays")
        scans = []
        for n, a in zip(names, arrays, strict=True):
            a = np.asarray(a, dtype=np.float64)
            if a.ndim != 2 or a.shape[1] != 3:
                raise InputError(f"{n}: points must be an (N, 3) array, got {a.shape}")
            ok = np.all(np.isfinite(a), axis=1)
            if ok.sum() < cfg.min_points:
                raise InputError(f"{n}: {int(ok.sum())} valid points, need {cfg.min_points}")
            scans.append(
                Scan(name=n, path=Path(n), points=a[ok], num_dropped_nonfinite=int((~ok).sum()))
            )
        src = None
    if len(scans) < 2:
        raise InputError(f"{source}: {what} needs at least 2 scans, found {len(scans)}")
    return scans, src, truth


def _pair_table(results: list[PairResult], tracks, weights) -> list[dict]:
    w_of = {(int(i), int(j)): float(w) for (i, j), w in zip(tracks.pairs, weights, strict=True)}
    rows = []
    for r in results:
        rows.append(
            {
                "scans": list(r.names),
                "accepted": bool(r.accepted),
                "reason": r.reason,
                "overlap_ratio": r.overlap_ratio,
                "inlier_rmse": r.inlier_rmse,
                "num_correspondences": int(r.num_correspondences),
                "fitness": r.fitness,
                "residual_ratio": r.residual_ratio,
                "free_space_violation": r.free_space_violation,
                "unseen_violation": r.unseen_violation,
                "final_weight": w_of.get((r.i, r.j), 0.0) if r.accepted else 0.0,
                "seconds": r.seconds,
            }
        )
    return rows


def _evaluate(reg: Registration, pre, truth) -> None:
    """Overlap residual on the raw points; errors against ground truth when given."""
    if not reg.T_world_scan:
        return
    idx = {s.name: i for i, s in enumerate(reg.scans)}
    world = [transform_points(T, reg.scans[idx[n]].points) for n, T in reg.T_world_scan.items()]
    spacing = float(np.median([p.noise for p in pre])) if pre else 0.0
    thresh = max(2.0 * pre[0].fine_voxel_size, 10 * spacing)
    common = [n for n in reg.T_world_scan if n in (truth or {})]
    truth_residual = None
    if len(common) >= 2:  # the truth's own residual on a second thread (same numbers)
        tw = [transform_points(np.asarray(truth[n]), reg.scans[idx[n]].points) for n in common]
        pool = ThreadPoolExecutor(1)
        truth_residual = pool.submit(
            overlap_residual, tw, thresh, max_points=2000, seed=reg.config.seed
        )
        pool.shutdown(wait=False)
    reg.overlap = overlap_residual(world, thresh, max_points=2000, seed=reg.config.seed)
    if len(common) >= 2:
        est = np.stack([reg.T_world_scan[n] for n in common])
        tru = np.stack([np.asarray(truth[n]) for n in common])
        err = pose_errors(est, tru)
        centroids = np.stack([reg.scans[idx[n]].points.mean(axis=0) for n in common])
        at_centroid = pose_errors(est, tru, at=centroids).translation
        reg.truth_errors = {
            "scans": common,
            "rotation_deg": err.rotation_deg.tolist(),
            "translation": err.translation.tolist(),
            **err.summary(),
            "translation_at_centroid": at_centroid.tolist(),
            "translation_at_centroid_max": float(at_centroid.max()),
        }
        reg.truth_errors["truth_overlap_residual"] = truth_residual.result()
