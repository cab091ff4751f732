"""register(): a folder of scans in, globally aligned poses out. Reads as its stages:

    load -> preprocess -> pair graph -> global stage -> evaluate

The mode (:class:`~mvreg.pipeline.stages.UnorderedMode` by default, the sequence mode of
:mod:`mvreg.sequence` for ``--sequence``) supplies preprocessing, the pair graph and the
evaluation; :func:`run_pipeline` is the one list of stages both run.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mvreg.config import RegisterConfig, load_config
from mvreg.geometry import transform_points
from mvreg.globalstage.solve import TrackSolver
from mvreg.globalstage.stage import GlobalContext, GlobalStage
from mvreg.globalstage.verify import ScanVerification
from mvreg.pipeline.load import load_source
from mvreg.pipeline.result import Registration, pair_table
from mvreg.pipeline.run import Run
from mvreg.pipeline.stages import Mode, UnorderedMode


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
        config: a RegisterConfig (default: the defaults); ``overrides`` apply on top of
            it (dotted keys, e.g. ``**{"solve.solver": "gpm"}``, or plain ``seed=1``).
        names: names of the arrays when ``source`` is a list.
        recorder: a mvreg.viz Recorder (default: none).
        progress: an object with stage(name, total) / advance(n) / done() (CLI: rich bars).
        truth: {name: 4x4 T_world_scan} to evaluate against; by default read from
            ``ground_truth.json`` in the folder. Used only to evaluate, never to solve.
        pair_hook: optional ``f(pre, results) -> results`` applied after pairwise
            alignment (benchmarks and tests use it to inject wrong pairs).
    """
    # Overrides apply on top of a given configuration too (``config=cfg, seed=1``).
    cfg = config if config is not None and not overrides else load_config(base=config, **overrides)
    with Run(cfg, recorder, progress) as run:
        return run_pipeline(run, UnorderedMode(pair_hook), source, names, truth)


def run_pipeline(run: Run, mode: Mode, source, names=None, truth=None, result_type=Registration):
    """The stages of every run; ``mode`` decides preprocessing, pairing and evaluation."""
    cfg, rec, prog = run.cfg, run.recorder, run.progress
    loaded = load_source(
        source, names, cfg.min_points, cfg.max_points_per_scan, truth, prog, mode.what
    )
    scans, truth = loaded.scans, loaded.truth
    run.timed("load")
    rec.log_config(cfg.model_dump(mode="json"))
    rec.log_raw_scans([s.name for s in scans], [s.points for s in scans])

    scales, pre = mode.preprocess(run, scans)
    run.timed("preprocess")
    graph = mode.pair_graph(run, scans, pre, scales)

    prog.stage("global solve")
    ctx = GlobalContext(
        cfg, scales.voxel, run.local, TrackSolver(cfg.solve, cfg.seed, run.on_iteration), scans
    )
    t_verify = time.perf_counter()
    out, verification, dropped = verified_passes(run, mode, ctx, pre, scales, graph)
    run.timings["verify_with_resolves"] = time.perf_counter() - t_verify
    prog.done()

    names_all = [s.name for s in scans]
    sol = out.solution
    kept = [] if sol is None else [i for i in sorted(sol.T_world_scan) if i not in dropped]
    T = {names_all[i]: sol.T_world_scan[i] for i in kept}
    status = scan_status(names_all, T, verification, dropped)
    reg = result_type(
        scan_names=names_all,
        T_world_scan=T,
        unregistered=[n for n in names_all if status[n]["status"] == "unregistered"],
        unverified=[n for n in names_all if status[n]["status"] == "unverified"],
        undetermined=[n for n in names_all if status[n]["status"] == "undetermined"],
        verification=status,
        solve=None if sol is None else sol.result,
        pairs=pair_table(out.results, out.tracks, out.weights, graph.columns),
        config=cfg,
        scales=scales,
        timings=run.timings,
        robust_log=out.robust_log,
        refine_log=out.refine_log,
        joint_icp=out.joint_icp,
        scans=scans,
        source=loaded.source,
        skipped_files=loaded.skipped,
    )
    mode.evaluate(run, reg, pre, out.results, truth)
    run.timed("evaluate")
    run.finish()
    if T:
        idx = [names_all.index(n) for n in T]
        rec.log_aligned(list(T), [scans[i].points for i in idx], list(T.values()))
        if cfg.output.record_pair_correspondences and rec.enabled:
            record_pairs(rec, sol, names_all)
    return reg


def verified_passes(run: Run, mode: Mode, ctx, pre, scales, graph):
    """The global stage with verification (:meth:`GlobalStage.run_verified`); when scans
    are left without a verified pose and the mode has pairs to search again for them
    (``mode.recover``: one or more choices of pair results), a further pass on each, the
    one that verifies the most scans kept (a later pass only when it verifies more).
    Returns (outcome, verification, dropped) of the pass kept."""
    stage = GlobalStage(graph.plan)
    best = stage.run_verified(ctx, pre, graph.results, run.progress, run.timed)
    recover = getattr(mode, "recover", None)
    retries = None if recover is None else recover(run, pre, scales, graph.results, *best)
    for retry in retries or []:
        again = stage.run_verified(ctx, pre, retry, run.progress, run.timed)
        if _num_verified(*again[1:]) > _num_verified(*best[1:]):
            best = again
    return best


def _num_verified(verification: dict, dropped) -> int:
    return sum(v.status == "verified" and s not in dropped for s, v in verification.items())


def record_pairs(rec, sol, names: list[str]) -> None:
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


def scan_status(names: list[str], T: dict, verification: dict, dropped) -> dict[str, dict]:
    """{scan name: verification dict} for every scan: ``verified`` (in ``T``),
    ``unverified`` / ``undetermined`` (dropped by verification, with the reason) or
    ``unregistered`` (no accepted pair connects it to the others)."""
    out = {}
    for k, n in enumerate(names):
        v = verification.get(k)
        if v is None or (n not in T and k not in dropped):
            v = ScanVerification("unregistered", "not connected to the others by accepted pairs")
        out[n] = v.to_dict()
    return out
