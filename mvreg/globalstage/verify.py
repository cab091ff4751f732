"""Per-scan pose verification: is each registered scan's final pose backed by evidence
independent of the one pair that may have placed it?

The certificate of the global solve proves the solve optimal *for the accepted pairs*; it
says nothing about whether those pairs are right. A scan hung on a single wrong pair (a
fitness-0.29 pair that nothing else contradicts) or a scan of a rotationally symmetric
object (whose rotation about the axis no data fixes) is solved exactly and certified.
This module checks each scan's final pose against independent evidence.

Contract (pure functions on arrays, preprocessed scans and pair results; no I/O):

* :func:`verify_scans` takes the final poses ``{scan index: (4, 4) T_world_scan}``, the
  preprocessed scans, the pair results and the final pair weights, and returns a
  :class:`ScanVerification` per registered scan, with ``status``:

  - ``"verified"``: the pose is confirmed by

    (a) a cycle: the scan has accepted pairs of positive final weight whose own relative
        pose agrees with the final relative pose (median motion of the overlap within
        ``agree_voxels`` feature voxels, :func:`mvreg.refine.pair_disagreements`) to two
        different scans that are connected to each other through agreeing pairs without
        it, so its pose closes a cycle of independently estimated pairs; or
    (b) a scan-to-model check under the final pose against the union of the other
        registered scans: overlap share and residual passing the pairwise acceptance rule
        (``AlignConfig.min_overlap_ratio``, ``max_residual_ratio`` x the scans' noise),
        tight support from at least two other scans (so not only the single partner pair);

    and, for (b), both free-space tests
    (:func:`mvreg.pairwise.align.free_space_violation`,
    :func:`~mvreg.pairwise.align.unseen_violation`) within the pairwise limits against
    every scan of its model (reported), a violation (above the pairwise limits loosened
    by ``coarse_gate_slack``) counting as a conflict with a scan that shares tight matches
    with it; a conflict counts against this scan when the other one's own evidence is
    stronger (cycle > model check > neither). The tests are run and reported for
    cycle-confirmed scans too, but do not overrule a cycle; more than half the facing
    points in any other scan's free space does, on the weaker side (or both, on a tie:
    :mod:`mvreg.globalstage.conflicts`).

  - ``"unverified"`` (``reason`` says which evidence is missing or contradicts it);
  - ``"undetermined"``: some degree of freedom of the scan against the model is not
    fixed by the data (``degenerate_dof`` names it: rotation about an axis through a
    point, or translation along a direction). Detected for every scan, cycle-confirmed or
    not, from the 6x6 point-to-plane normal matrix of its tight matches to the model
    (rotation columns scaled by the rms radius of the matched points, so both blocks are
    in squared length per point): a motion of one feature voxel along the weakest
    eigenvector raises the rms point-to-plane residual by ``sqrt(lambda_min)`` voxels; when
    that is below the scans' noise (``lambda_min < (noise / voxel)**2``), the direction is
    a candidate, and it is undetermined when point-to-plane ICP against the model, started
    ``probe_voxels`` (3) feature voxels along it, does not come back (median point motion
    above ``agree_voxels``) and lands on a fit as good (:func:`equally_good`: residual
    within the acceptance rule and at most 1.25x the final one's plus its sampling spread,
    overlap share at least 0.9x the final one's minus three binomial standard errors):
    the data cannot tell the two poses apart. Only continuous freedoms are found this way;
    a discrete symmetry (a knot turned 120 or 180 deg onto itself) is found by
    :func:`search_alternatives` (below).

With ``discrete``, :func:`search_alternatives` then searches every verified scan, and
each side of a pair that alone joins two groups of agreeing scans (:func:`bridge_groups`,
moved as one), for a second, distant pose (:mod:`mvreg.globalstage.model_search`): one
that fits as well makes the scan ``"undetermined"`` (``degenerate_dof`` names the discrete
turn), one that fits better ``"unverified"``. Last, a verified scan whose agreeing pairs
all link it to undetermined scans is undetermined too
(:func:`~mvreg.globalstage.probes.resting_on_undetermined`).

"The other scans" are, for each scan, at most
:data:`~mvreg.globalstage.scan_model.MODEL_SCANS` of them, those that cover most of its
surface (:func:`~mvreg.globalstage.scan_model.model_members`), so the cost grows with the
scans, not with their square. Every threshold comes from the data (feature voxel, noise,
point counts) or the pairwise acceptance rule; none is fitted to an object.

:func:`verify_and_resolve` is the pipeline loop: scans that are not verified leave the
registered set, the rest is solved again without the pairs touching them (so a wrong pair
cannot drag the others through the gauge), and verified again (a few rounds at most); the
search for second poses runs once, when a round drops nothing else. Before scans are
dropped, contradictions between scans joined only through single pairs (bridges of the
agreeing pairs) are settled by cutting those pairs
(:func:`mvreg.globalstage.graph.conflict_cuts`): the largest part is solved again and the
parts cut off keep their own relative poses, to be placed on it as groups.
:mod:`mvreg.globalstage.place` then tries to place the scans left out on the model of the
verified ones.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from mvreg.config.align import AlignConfig
from mvreg.executor import single_threaded_blas
from mvreg.geometry import transform_points
from mvreg.globalstage.conflicts import free_space_conflicts, settle_conflicts
from mvreg.globalstage.graph import bridge_groups, conflict_cuts, main_block, on_cycle, one_side
from mvreg.globalstage.model_search import (
    GROUP_CANDIDATES,
    axis_turns,
    distant_alternative,
    self_symmetry,
)
from mvreg.globalstage.probes import (
    degenerate_direction,
    on_one_plane,
    outnumbered_by_turns,
    relative_residual_outliers,
    resting_on_undetermined,
    unsettled,
)
from mvreg.globalstage.robust import pair_disagreements
from mvreg.globalstage.scan_model import MODEL_SCANS, Overlaps, model_fit, model_members, scan_model

NOTE = (
    "the certificate proves the global solve optimal for the accepted pairs; verification "
    "checks each scan's pose against independent evidence"
)


@dataclass
class ScanVerification:
    """Evidence for one scan's final pose (see the module docstring)."""

    status: str  # "verified" | "unverified" | "undetermined" | "unregistered"
    reason: str = ""
    evidence: str = ""  # "cycle" | "model" | ""
    agreeing_pairs: list[str] = field(default_factory=list)
    model_overlap: float | None = None
    model_residual_ratio: float | None = None
    free_space_violation: float | None = None
    unseen_violation: float | None = None
    degenerate_dof: str | None = None
    supporting_scans: list[str] = field(default_factory=list)
    # Scans whose views contradict this one under the poses checked (free-space tests
    # against scans it shares surface with; before conflicts are settled). Not reported.
    conflicting: list[int] = field(default_factory=list, repr=False)

    def to_dict(self) -> dict:
        def num(x):
            return None if x is None or not np.isfinite(x) else float(x)

        return {
            "status": self.status,
            "reason": self.reason,
            "evidence": self.evidence,
            "agreeing_pairs": list(self.agreeing_pairs),
            "model_overlap": num(self.model_overlap),
            "model_residual_ratio": num(self.model_residual_ratio),
            "free_space_violation": num(self.free_space_violation),
            "unseen_violation": num(self.unseen_violation),
            "degenerate_dof": self.degenerate_dof,
            "supporting_scans": list(self.supporting_scans),
        }


# ---------------------------------------------------------------------------- evidence (a)


def agreeing_graph(
    pre: Sequence,
    results: Sequence,
    pair_weight: dict[tuple[int, int], float],
    T_world_scan: dict[int, np.ndarray],
    voxel: float,
    agree_voxels: float = 1.0,
) -> dict[int, set[int]]:
    """{scan: partners} over accepted pairs of positive final weight whose own pose agrees
    with the final relative pose within ``agree_voxels`` feature voxels."""
    dis = pair_disagreements(pre, results, T_world_scan, voxel)
    graph: dict[int, set[int]] = {s: set() for s in T_world_scan}
    for (i, j), d in dis.items():
        if pair_weight.get((i, j), 0.0) > 0 and d <= agree_voxels * voxel:
            graph[i].add(j)
            graph[j].add(i)
    return graph


# ---------------------------------------------------------------------------- verify


def verify_scans(
    pre: Sequence,
    results: Sequence,
    pair_weight: dict[tuple[int, int], float],
    T_world_scan: dict[int, np.ndarray],
    voxel: float,
    align_cfg: AlignConfig | None = None,
    agree_voxels: float = 1.0,
    discrete: bool = True,
    executor=None,
) -> dict[int, ScanVerification]:
    """A :class:`ScanVerification` per registered scan (module docstring).

    Args:
        pre: preprocessed scans (all of them; indices as in ``results``).
        results: pair results (``PairResult``: ``i``, ``j``, ``accepted``, ``T_i_j``).
        pair_weight: {(i, j): final weight} of the accepted pairs used in the solve.
        T_world_scan: {scan index: (4, 4)} final poses of the registered scans.
        voxel: feature voxel size.
        align_cfg: the pairwise acceptance rule (limits reused here).
        agree_voxels: a pair agrees with the final poses within this many feature voxels.
        discrete: also search each scan against the others for a distant pose that fits
            as well (:mod:`mvreg.globalstage.model_search`).
        executor: runs the checks of the scans (in-process threads; each check is a pure
            function of its scan, so the result does not depend on it); default: in turn.
    """
    acfg = align_cfg or AlignConfig()
    scans = sorted(T_world_scan)
    if not scans:
        return {}
    graph = agreeing_graph(pre, results, pair_weight, T_world_scan, voxel, agree_voxels)
    main = main_block(graph)
    cycle = on_cycle(graph) & main
    members = model_members(pre, T_world_scan, 2.0 * voxel)

    def check(s):
        return _check_scan(
            s, pre, T_world_scan, graph, cycle, main, voxel, acfg, agree_voxels, members[s]
        )

    checked = _map(executor, check, scans)
    out = {s: c[0] for s, c in zip(scans, checked, strict=True)}
    conflicts = {s: c[1] for s, c in zip(scans, checked, strict=True)}
    for s in scans:
        out[s].conflicting = sorted({c[0] for c in conflicts[s]})
    settle_conflicts(out, conflicts, scans)
    relative_residual_outliers(out, pre, acfg)
    if discrete:
        search_alternatives(out, graph, pre, T_world_scan, voxel, acfg, results, executor)
    resting_on_undetermined(out, graph, [p.name for p in pre])
    return out


def _map(executor, fn, items) -> list:
    """``fn`` over ``items`` in order: on ``executor`` (threads, BLAS on one thread each:
    the limit is process-wide, so it is set before they start) or in turn."""
    if executor is None:
        return list(map(fn, items))
    with single_threaded_blas():
        return executor.map(fn, list(items))


def _mark(v: ScanVerification, alt, group: str) -> None:
    v.status = "unverified" if alt.better else "undetermined"
    v.evidence = ""
    v.degenerate_dof = None if alt.better else f"a discrete turn of {alt.angle_deg:.0f} deg"
    v.reason = (f"moved as one with {group}: " if group else "") + alt.describe()


def _mark_symmetric(out, verified, sym) -> None:
    turn = f"{sym.angle_deg:.0f} deg"
    for s in verified:
        v = out[s]
        v.status, v.evidence = "undetermined", ""
        v.degenerate_dof = f"a symmetry of the registered scans: a turn of {turn}"
        v.reason = (
            f"the registered scans map onto themselves turned {turn} (overlap "
            f"{sym.overlap:.2f}): which symmetric place each scan takes is not fixed by the data"
        )


def search_alternatives(
    out, graph, pre, T_world_scan, voxel, acfg, results=(), executor=None
) -> None:
    """First the verified scans as a whole for a symmetry (a motion mapping them onto
    themselves: :func:`mvreg.globalstage.model_search.self_symmetry`; then every one is
    ``undetermined``); else every verified scan, then every group of verified scans that
    agree with each other but hang on the rest by one pair (:func:`bridge_groups`; each
    side of the pair moved as one rigid body, the smaller side marked), against the model
    of the others for a second pose
    (:func:`mvreg.globalstage.model_search.distant_alternative`); mark those that have one
    ``undetermined`` (as good) or ``unverified`` (better). ``out``: {scan:
    ScanVerification}, changed in place; ``graph``: the agreeing pairs."""
    scans = sorted(T_world_scan)
    verified = {s: T_world_scan[s] for s in scans if out[s].status == "verified"}
    turns = []
    if len(verified) >= 3:
        whole = scan_model(pre, verified, sorted(verified))
        sym = self_symmetry(pre, verified, whole, voxel, acfg)
        if sym is not None:
            _mark_symmetric(out, verified, sym)
            return
        turns = axis_turns(whole.points, whole.normals)  # a near axis of revolution
    near = Overlaps(pre, T_world_scan, 2.0 * voxel) if len(scans) > MODEL_SCANS + 1 else None
    members = model_members(pre, T_world_scan, 2.0 * voxel, near=near)

    def search(s):
        others = members[s]
        model = scan_model(pre, T_world_scan, others)
        # The pose hypotheses of its own pairs too, for cycle-confirmed scans as well: on a
        # near-symmetric shape wrong pairs close cycles (fuze sparse seed 0: a triangle
        # of two wrong pairs put one view 133 deg off, "cycle"-verified).
        return distant_alternative(
            [s], pre, T_world_scan, others, model, voxel, acfg, results=results, turns=turns
        )

    todo = [s for s in scans if out[s].status == "verified" and len(members[s]) >= 2]
    for s, alt in zip(todo, _map(executor, search, todo), strict=True):
        if alt is not None:
            _mark(out[s], alt, "")
    # Beyond MODEL_SCANS + 1 scans, only the scans facing across (a chain: a bridge each)
    for group, side in bridge_groups(graph):
        if any(out[s].status != "verified" for s in group):
            continue
        # Each side against the other: a second pose's fit is measured on the moved side's
        # points, so one side's may pass and the other's fall just short (teapot sparse
        # seed 1: 0.35 vs 0.32 against half of 0.64). The smaller side is given up.
        for moved in (group, side):
            others = [k for k in scans if k not in moved]
            if near is not None:
                moved, others = near.facing(moved, others), near.facing(others, moved)
            if len(others) < 2 or not moved:
                continue
            if _moved_as_one(out, group, moved, others, pre, T_world_scan, voxel, acfg,
                             results, turns):  # fmt: skip
                break
    _search_outnumbered(out, pre, T_world_scan, voxel, acfg, results, turns, near)
    outnumbered_by_turns(out)


def _search_outnumbered(out, pre, T_world_scan, voxel, acfg, results, turns, near) -> None:
    """The verified scans moved as one against the model of the undetermined ones, when
    these are more: a block that agrees with itself cannot confirm itself (quadknot dense
    seed 1: four scans closing cycles in a copy turned 120-180 deg, the six others each
    with a turned second pose). The smaller side is moved, as for a bridge."""
    moved = [s for s in sorted(T_world_scan) if out[s].status == "verified"]
    others = [s for s in sorted(T_world_scan) if out[s].status == "undetermined"]
    if near is not None:
        moved, others = near.facing(moved, others), near.facing(others, moved)
    if not moved or len(others) < max(2, len(moved) + 1):
        return
    _moved_as_one(out, moved, moved, others, pre, T_world_scan, voxel, acfg, results, turns)


def _moved_as_one(out, group, moved, others, pre, T_world_scan, voxel, acfg, results, turns):
    """Search the scans ``moved`` as one rigid body against the model of ``others``
    (:func:`~mvreg.globalstage.model_search.distant_alternative`, ``GROUP_CANDIDATES``
    motions); with a second pose, mark every scan of ``group``. Whether one was found."""
    model = scan_model(pre, T_world_scan, others)
    alt = distant_alternative(
        moved, pre, T_world_scan, others, model, voxel, acfg, results=results, turns=turns,
        max_refined=GROUP_CANDIDATES,
    )  # fmt: skip
    if alt is None:
        return False
    names = [p.name for p in pre]
    for s in group:
        _mark(out[s], alt, ", ".join(names[k] for k in group if k != s))
    return True


def _check_scan(s, pre, T_world_scan, graph, cycle, main, voxel, acfg, agree_voxels, others):
    """(ScanVerification of scan ``s`` before conflicts are settled, its conflicts),
    checked against the scans ``others`` (:func:`model_members`).

    Outside the main block of agreeing pairs (:func:`main_block`), only support from scans
    of the main block counts: a group that agrees with itself cannot confirm itself. With
    no block at all (the agreeing pairs form a tree), only support from one side of the
    scan counts (:func:`mvreg.globalstage.graph.one_side`): scans on two sides are placed
    relative to each other through this scan alone, so they cannot confirm it."""
    names = [p.name for p in pre]
    v = ScanVerification(status="verified", agreeing_pairs=[names[k] for k in sorted(graph[s])])
    T = T_world_scan[s]
    pts = transform_points(T, pre[s].fine_points)
    nrm = pre[s].fine_normals @ T[:3, :3].T
    model = scan_model(pre, T_world_scan, others)
    if model is None:
        v.status, v.reason = "unverified", "no other registered scan to check it against"
        return v, []
    overlap, ratio, tight, idx, noise = model_fit(model, pts, nrm, pre[s].noise, voxel, acfg)
    v.model_overlap, v.model_residual_ratio = overlap, ratio
    owners, counts = np.unique(model.owner[idx[tight]], return_counts=True)
    support = [int(k) for k, n in zip(owners, counts, strict=True) if n >= acfg.min_correspondences]
    v.supporting_scans = [names[k] for k in support]
    conflicts = free_space_conflicts(v, s, others, support, pre, T_world_scan, names, acfg)
    dof = degenerate_direction(model, pts, nrm, tight, idx, noise, voxel, acfg, agree_voxels)
    if dof is not None:
        v.status, v.degenerate_dof = "undetermined", dof
        v.reason = f"the other scans do not fix its {dof.split(' ')[0]}"
        return v, conflicts
    if s in cycle:
        v.evidence = "cycle"
        return v, conflicts
    drift = unsettled(model, pts, nrm, noise, voxel, acfg, agree_voxels)
    if drift:
        v.status, v.reason = "unverified", drift
        return v, conflicts
    if main and s not in main:
        support = [k for k in support if k in main]
    elif not main:
        support = one_side(graph, s, support)
    problems = _model_problems(overlap, ratio, support, graph[s], v, names, acfg)
    if not problems:
        problems = _unpinned(pts, nrm, pre[s].noise, support, pre, T_world_scan, voxel, acfg)
    if problems:
        v.status, v.reason = "unverified", "; ".join(problems)
    return v, conflicts


def _unpinned(pts, nrm, noise_s, support, pre, T_world_scan, voxel, acfg) -> list[str]:
    """Whether the supporting scans alone (placed independently of this one) fix every
    degree of freedom of the scan (world ``pts``, ``nrm``): :func:`on_one_plane`, then
    :func:`degenerate_direction`, against their model. A scene's ground fixes height, roll
    and pitch, not heading, while the rest of the fit comes from scans that hang on the
    same pair (60 LiDAR stations: six 143 deg off, later four 41.6 deg off, "verified")."""
    model = scan_model(pre, T_world_scan, support)
    _, _, tight, idx, noise = model_fit(model, pts, nrm, noise_s, voxel, acfg)
    if np.count_nonzero(tight) < 2 * acfg.min_correspondences:
        return [f"only {np.count_nonzero(tight)} close matches with the scans placed without it"]
    dof = on_one_plane(model, pts, nrm, tight, idx, voxel)
    dof = dof or degenerate_direction(model, pts, nrm, tight, idx, noise, voxel, acfg)
    if dof is None:
        return []
    return [f"the scans placed without it fix only part of its pose, not its {dof}"]


def _model_problems(overlap, ratio, support, agreeing, v, names, acfg) -> list[str]:
    """Why a scan not on a cycle fails the scan-to-model check (empty: it passes)."""
    problems = []
    if overlap < acfg.min_overlap_ratio:
        problems.append(f"overlap with the other scans {overlap:.2f} < {acfg.min_overlap_ratio}")
    if not ratio <= acfg.max_residual_ratio:
        problems.append(
            f"residual against the other scans {ratio:.1f}x the noise "
            f"(limit {acfg.max_residual_ratio})"
        )
    if len(support) < 2:
        problems.append(
            "supported by "
            + (f"only {names[support[0]]}" if support else "no other scan")
            + (
                f" (its single pair with {v.agreeing_pairs[0]} is not confirmed by a cycle)"
                if len(agreeing) == 1
                else ""
            )
        )
    return problems


# ---------------------------------------------------------------------------- pipeline loop


def verify_and_resolve(
    pre: Sequence,
    results: Sequence,
    solved,
    resolve: Callable,
    voxel: float,
    align_cfg: AlignConfig | None = None,
    agree_voxels: float = 1.0,
    max_rounds: int = 3,
    discrete: bool = True,
    executor=None,
):
    """Verify, drop the scans that are not verified, re-solve the rest without the pairs
    touching them, and verify again (at most ``max_rounds`` re-solves). With ``discrete``,
    the search against the model of the others (:mod:`mvreg.globalstage.model_search`)
    runs when a round finds nothing else to drop (it is the costly part), once per set.

    ``solved``: the pipeline's state after its global stage, with attributes
    ``T_world_scan`` ({scan index: (4, 4)}) and ``pair_weight`` ({(i, j): weight}).
    ``resolve(results)``: runs the global stage again on ``results`` and returns a new
    state of the same kind. Returns (state, {scan index: ScanVerification} for every scan
    that had a pose at some point, the dropped scan indices, the parts split off where
    views contradicted each other: [{scan: T_world_scan}], poses of the solve before the
    split, every scan of them dropped). The search runs again on a
    set that settles after a search dropped scans (their pairs no longer hold the others in
    place, so a group may now show its better pose). The caller reports no pose
    for a dropped scan (after the last allowed round the state may still hold one).
    """
    dropped: dict[int, ScanVerification] = {}
    groups: list[dict[int, np.ndarray]] = []
    rounds = 0
    searched: set | None = None  # the set the search against the model last ran on

    def remaining() -> frozenset:
        return frozenset(s for s in solved.T_world_scan if s not in dropped)

    acfg = align_cfg or AlignConfig()

    def check(search: bool, ver: dict | None = None) -> tuple[dict, dict]:
        T = {s: T for s, T in solved.T_world_scan.items() if s not in dropped}
        if ver is None:
            ver = verify_scans(
                pre, results, solved.pair_weight, T, voxel, acfg, agree_voxels, False, executor
            )
        if search:
            graph = agreeing_graph(pre, results, solved.pair_weight, T, voxel, agree_voxels)
            search_alternatives(ver, graph, pre, T, voxel, acfg, results, executor)
        return ver, {s: v for s, v in ver.items() if v.status != "verified"}

    while True:
        ver, bad = check(False)
        cut, graph = _cut_links(ver, pre, results, solved, voxel, agree_voxels) if bad else ([], {})
        if cut and rounds < max_rounds:
            # Split where the views contradict each other, re-solve the largest part;
            # the other parts are placed on it afterwards, each moved as one
            # (:func:`mvreg.globalstage.place.place_leftovers`).
            rounds += 1
            results = [r for r in results if frozenset((r.i, r.j)) not in cut]
            before = solved.T_world_scan
            solved = resolve([r for r in results if r.i not in dropped and r.j not in dropped])
            off = sorted(set(before) - set(solved.T_world_scan) - dropped.keys())
            for s in off:
                dropped[s] = _cut_off(ver[s], cut, pre)
            groups += _parts(graph, cut, off, before)
            continue
        if not bad and discrete and remaining() != searched:
            searched = remaining()  # a settled set not searched yet (a drop changes it)
            ver, bad = check(True, ver)
        if not bad:
            break
        dropped.update(bad)
        if len(remaining()) < 2 or rounds == max_rounds:
            break
        rounds += 1
        kept = [r for r in results if r.i not in dropped and r.j not in dropped]
        solved = resolve(kept)
    if discrete and remaining() != searched and len(remaining()) >= 2:
        # Rounds ran out before the set settled: search the survivors all the same.
        ver, bad = check(True)
        dropped.update(bad)
    ver = {s: v for s, v in ver.items() if s not in dropped and s in solved.T_world_scan}
    ver.update(dropped)
    return solved, ver, sorted(dropped), [g for g in groups if g.keys() <= dropped.keys()]


def _cut_links(ver, pre, results, solved, voxel, agree_voxels) -> tuple[list[frozenset], dict]:
    """The agreeing pairs to cut (:func:`mvreg.globalstage.graph.conflict_cuts`) so that no
    two scans whose views contradict each other stay joined through a single pair. Ties go
    against the more ambiguous pair: more distinct hypotheses that passed the acceptance
    rule, then one found by the rotation search (no descriptor consensus), then the lower
    final weight; before all these, a pair of a scan that lost a conflict
    (:func:`~mvreg.globalstage.conflicts.settle_conflicts`) goes first."""
    T = {s: T for s, T in solved.T_world_scan.items() if s in ver}
    graph = agreeing_graph(pre, results, solved.pair_weight, T, voxel, agree_voxels)
    conflicts = {(s, k) for s, v in ver.items() for k in v.conflicting if k in graph}
    if not conflicts:
        return [], graph
    by_pair = {frozenset((r.i, r.j)): r for r in results if r.accepted}

    def weakness(edge):
        r = by_pair.get(edge)
        if r is None:
            return (0, 0, 0, 0.0)
        w = solved.pair_weight.get((r.i, r.j), solved.pair_weight.get((r.j, r.i), 0.0))
        lost = any(ver[s].status != "verified" and ver[s].conflicting for s in edge)
        hyp = int(r.stats.get("hypotheses_accepted", 1))
        return (int(lost), hyp, int(bool(r.stats.get("search"))), -w)

    return conflict_cuts(graph, conflicts, weakness), graph


def _parts(graph, cut, scans, T_world_scan) -> list[dict[int, np.ndarray]]:
    """The scans ``scans`` split into the parts the agreeing ``graph`` joins without the
    ``cut`` pairs, each with its poses {scan: T_world_scan} (relative poses within a part
    are what its own pairs say)."""
    scans, out = set(scans), []
    while scans:
        part, todo = set(), [min(scans)]
        while todo:
            a = todo.pop()
            if a in part:
                continue
            part.add(a)
            todo += [b for b in graph.get(a, ()) if b in scans and frozenset((a, b)) not in cut]
        scans -= part
        out.append({s: T_world_scan[s] for s in sorted(part)})
    return out


def _cut_off(v: ScanVerification, cut, pre) -> ScanVerification:
    names = [p.name for p in pre]
    links = ", ".join(f"{names[a]}-{names[b]}" for a, b in (sorted(e) for e in cut))
    return ScanVerification(
        status="unverified",
        reason=(
            f"its link to the largest consistent part was cut ({links}): views on the two "
            "sides contradict each other (free-space tests)"
        ),
        agreeing_pairs=v.agreeing_pairs,
    )
