"""Stage 3c: several hypotheses per pair, one chosen per pair jointly by agreement.

On sparse scans of machined parts the pose each pair keeps by itself is often a turn or a
flip that passes every pairwise test (a part's faces look alike from many sides), while
the right pose is among the pair's other accepted hypotheses (feature RANSAC's, and the
rotation search's distinct survivors). One pair cannot tell them apart; several views
together can: the right poses agree around cycles, the turns mostly do not.

:func:`joint_choice` places scans one at a time from trusted poses (``anchors``: the scans
a first pass verified; without any, the best triangle of hypotheses that close within the
tolerance). A scan is placed only at a pose that at least ``min_agreeing`` of its pairs
with placed scans agree on (each through one of its accepted hypotheses), so every scan it
places is on a cycle; among scans that qualify, the one with the most agreeing pairs, then
the most overlap, goes first. With the views' free-space tests (``views``, as the pipeline
runs it: :class:`_Views`), a pose that contradicts a placed scan's view is passed over, and
when no scan qualifies any more, a scan one pair places without contradicting any placed
view is taken; once the set stops growing, such a scan stays only where later scans closed
a cycle through it (every scan of a set but the anchors has two agreeing pairs within it),
and a triangle whose views contradict each other starts no set.

Agreement alone can prefer a consistent turn: on sparse teapot views (seed 1) scan 0 was
flipped 180 deg against scans 5, 6 and 9 by all three of its direct pairs, while its right
pose closed only longer cycles (0-4-5, 0-1-6); the flipped set of all ten scans had more
agreeing pairs (15) than the right one (13), but five pairs of it put surfaces in each
other's free space, the right one none.

Without anchors, the growth starts from each of the ``max_seeds`` closing triangles with
the most overlap, and the start that places the most scans, then with the most pairs
agreeing, is kept; the scans left are grown into further sets the same way (each in its
own frame) while a triangle of them closes. Each pair
within a set then keeps the hypothesis that agrees with the set's poses, and a pair
accepted before that none of its hypotheses agrees with is rejected. The global stage and
the verification run on the result as on any pairs: nothing placed here escapes the
per-scan checks.

:func:`search_hypotheses` gathers the hypotheses: the accepted ones each aligner already
verified (``stats["accepted_hypotheses"]``, :func:`~mvreg.pairwise.decision.choose`) and,
for the pairs given, those of the rotation search. Deterministic: fixed orders, ties by
index.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from mvreg.config.align import AlignConfig, SearchConfig
from mvreg.executor import Executor
from mvreg.geometry import invert_transform, transform_points
from mvreg.pairwise.aligners import make_aligner
from mvreg.pairwise.hypotheses import same_pose, scan_extent
from mvreg.pairwise.preprocess import PreprocessedScan
from mvreg.pairwise.result import PairResult, pair_result
from mvreg.pairwise.scoring import score_alignment, view_conflicts
from mvreg.scales import Scales

Hypotheses = dict[tuple[int, int], list[tuple[np.ndarray, dict | None]]]
"""{(i, j): [(T_i_j, fine scores or None), ...]}: accepted hypotheses, best first."""


def accepted_hypotheses(r: PairResult) -> list[tuple[np.ndarray, dict | None]]:
    """The accepted hypotheses of one pair result, its kept pose first."""
    out = list(r.stats.get("accepted_hypotheses", []))
    if r.accepted and not any(np.allclose(r.T_i_j, K) for K, _ in out):
        out.insert(0, (r.T_i_j, None))
    return out


def search_hypotheses(
    pre: Sequence[PreprocessedScan],
    results: Sequence[PairResult],
    pairs: Sequence[tuple[int, int]],
    cfg: AlignConfig,
    search: SearchConfig,
    executor: Executor | int,
    *,
    scales: Scales | None,
    hyp: Hypotheses | None = None,
) -> Hypotheses:
    """Every pair's accepted hypotheses (those of ``hyp`` when given, else of the results),
    with those of the rotation search added for ``pairs`` (each searched once, in the order
    given). A pair whose result is already the rotation search's (``connect_unconnected``
    searched it with the same settings) is not searched again: the search is deterministic,
    so it would add nothing (a scan of noise next to three bunny views: 15.8 s)."""
    if hyp is None:
        hyp = {(r.i, r.j): accepted_hypotheses(r) for r in results}
    else:
        hyp = {e: list(hs) for e, hs in hyp.items()}
    done = {(r.i, r.j) for r in results if r.stats.get("search")}
    pairs = [p for p in pairs if p not in done]
    if not pairs:
        return hyp
    aligner = make_aligner("rotation-search", cfg, search, scales=scales, executor=executor)
    aligner.prepare(pre)
    for i, j in pairs:
        res = aligner.align(pre[i], pre[j], i=i, j=j)
        have = hyp.setdefault((i, j), [])
        for T, scores in accepted_hypotheses(res):
            if not any(np.allclose(T, K) for K, _ in have):
                have.append((T, scores))
    return hyp


class _Agreement:
    """Poses of scans from the placed ones through each pair's hypotheses."""

    def __init__(self, pre, hyp: Hypotheses, tol: float):
        self.hyp, self.tol = hyp, tol
        self.extent = [scan_extent(p.points) for p in pre]
        self.partners: dict[int, list[tuple[int, np.ndarray]]] = {}
        for (i, j), hs in sorted(hyp.items()):
            for T, _ in hs:  # T_i_j, and T_j_i = T_i_j^-1
                self.partners.setdefault(j, []).append((i, T))
                self.partners.setdefault(i, []).append((j, invert_transform(T)))

    def same(self, s: int, A: np.ndarray, B: np.ndarray) -> bool:
        centre, radius = self.extent[s]
        return same_pose(A, B, self.tol, centre, radius)

    def candidates(self, u: int, placed: dict) -> list[tuple[np.ndarray, set]]:
        """(pose of u, the placed partners agreeing on it) for every hypothesis of a pair
        of u with a placed scan."""
        via = [(p, placed[p] @ T) for p, T in self.partners.get(u, []) if p in placed]
        out = []
        for _, A in via:
            agree = {p for p, B in via if self.same(u, A, B)}
            out.append((A, agree))
        return out


class _Views:
    """Whether a pose of a scan contradicts the views of placed scans: the rule verification
    uses (:func:`~mvreg.pairwise.scoring.view_conflicts`), on the feature level.

    A conflict with a placed scan that shares surface with it (overlap at least
    ``min_overlap_ratio`` loosened by ``coarse_gate_slack``): either free-space share above
    its pairwise limit loosened the same way (the pose was not refined on that pair); with
    any placed scan: more than ``max_free_space_apart`` of the points in its free space.
    Results are kept per pair and relative pose (a pose within the agreement tolerance of
    one tested reads the same)."""

    def __init__(self, pre, cfg: AlignConfig, scales: Scales, agreement: _Agreement):
        self.pre, self.cfg, self.scales, self.agreement = pre, cfg, scales, agreement
        self.seen: dict[tuple[int, int], list[tuple[np.ndarray, bool]]] = {}

    def consistent(self, u: int, A: np.ndarray, placed: dict) -> bool:
        """Whether scan ``u`` at pose ``A`` contradicts none of the ``placed`` scans."""
        cu, ru = self.agreement.extent[u]
        centre = transform_points(A, cu[None])[0]
        for p, B in sorted(placed.items()):
            cp, rp = self.agreement.extent[p]
            if np.linalg.norm(transform_points(B, cp[None])[0] - centre) > ru + rp:
                continue  # too far apart to see each other
            T_p_u = invert_transform(B) @ A
            known = self.seen.setdefault((p, u), [])
            verdict = next((ok for T, ok in known if self.agreement.same(u, T, T_p_u)), None)
            if verdict is None:
                verdict = not self._conflict(p, u, T_p_u)
                known.append((T_p_u, verdict))
            if not verdict:
                return False
        return True

    def coherent(self, placed: dict) -> bool:
        """Whether no scan of ``placed`` contradicts another's view."""
        order = sorted(placed)
        return all(
            self.consistent(u, placed[u], {p: placed[p] for p in order[:k]})
            for k, u in enumerate(order)
        )

    def _conflict(self, p: int, u: int, T_p_u: np.ndarray) -> bool:
        cfg = self.cfg
        s = score_alignment(self.pre[p], self.pre[u], T_p_u, cfg, "feature", scales=self.scales)
        shares = bool(s["overlap_ratio"] >= cfg.min_overlap_ratio / cfg.coarse_gate_slack)
        # The gross rule applies here also to views without a sensor position (verification
        # spares those): this choice only ranks hypotheses, and a right pose it passes over
        # is still in the choice on agreement alone, which gets a pass too.
        fs, un = s["free_space_violation"], s["unseen_violation"]
        return bool(view_conflicts(fs, un, shares, cfg, sensors=True))


def _seeds(agreement: _Agreement, hyp: Hypotheses, overlap, limit: int, taken) -> list[dict]:
    """Up to ``limit`` triangles of hypotheses that close within the tolerance, most
    overlap first, none of whose scans is in ``taken``: {a: I, b: T_a_b, c: T_a_c} each."""
    found = []
    edges = {e for e, hs in hyp.items() if hs and not taken & set(e)}
    up: dict[int, set[int]] = {}  # a -> partners b > a (triangles in O(edges x degree))
    for a, b in edges:
        up.setdefault(a, set()).add(b)
    triangles = [
        (a, b, c) for a, b in sorted(edges) for c in sorted(up.get(a, set()) & up.get(b, set()))
    ]
    for a, b, c in triangles:
        score = overlap[(a, b)] + overlap[(b, c)] + overlap[(a, c)]
        for Tab, _ in hyp[(a, b)]:
            for Tbc, _ in hyp[(b, c)]:
                if any(agreement.same(c, Tab @ Tbc, Tac) for Tac, _ in hyp[(a, c)]):
                    found.append((-score, len(found), {a: np.eye(4), b: Tab, c: Tab @ Tbc}))
    return [f[2] for f in sorted(found, key=lambda f: f[:2])[:limit]]


def _grow(
    n: int, placed: dict, agreement: _Agreement, overlap, min_agreeing: int, taken, views=None
) -> dict:
    """Place scans one at a time (module docstring), none of ``taken``; the poses of all
    placed scans. With ``views`` (:class:`_Views`), a pose that contradicts a placed view
    is passed over, and when no scan has ``min_agreeing`` agreeing pairs left, one that a
    single pair places without contradicting any placed view is taken."""
    placed = dict(placed)
    banned: list[tuple[int, np.ndarray]] = []
    while True:
        ranked = []
        for u in range(n):
            if u in placed or u in taken:
                continue
            for A, agree in agreement.candidates(u, placed):
                key = (len(agree), sum(overlap.get((min(p, u), max(p, u)), 0.0) for p in agree))
                ranked.append((key, u, A))
        ranked.sort(key=lambda c: (-c[0][0], -c[0][1]))  # stable: ties in scan order
        floor = min_agreeing if views is None else 1
        chosen = None
        for (count, _), u, A in ranked:
            if count < floor:
                break
            if any(b == u and agreement.same(u, A, B) for b, B in banned):
                continue
            if views is not None and not views.consistent(u, A, placed):
                banned.append((u, A))
                continue
            chosen = (u, A)
            break
        if chosen is None:
            return placed
        placed[chosen[0]] = chosen[1]


def _agreeing(placed: dict, agreement: _Agreement, hyp: Hypotheses) -> list[tuple[int, int]]:
    """The pairs between placed scans that have a hypothesis agreeing with their poses."""
    out = []
    for (i, j), hs in hyp.items():
        if i in placed and j in placed:
            want = invert_transform(placed[i]) @ placed[j]
            if any(agreement.same(j, T, want) for T, _ in hs):
                out.append((i, j))
    return out


def _on_cycles(placed: dict, agreement: _Agreement, hyp: Hypotheses, keep, least: int) -> dict:
    """``placed`` without the scans (none of ``keep``) that fewer than ``least`` agreeing
    pairs join to the others, dropped until none is left: a scan one pair placed stays
    only where a later scan closed a cycle through it."""
    placed = dict(placed)
    while True:
        count = dict.fromkeys(placed, 0)
        for i, j in _agreeing(placed, agreement, hyp):
            count[i] += 1
            count[j] += 1
        weak = [s for s, c in count.items() if c < least and s not in keep]
        if not weak:
            return placed
        for s in weak:
            del placed[s]


def joint_choice(
    pre: Sequence[PreprocessedScan],
    results: Sequence[PairResult],
    hyp: Hypotheses,
    anchors: dict[int, np.ndarray],
    voxel: float,
    *,
    max_voxels: float = 2.0,
    min_agreeing: int = 2,
    max_seeds: int = 20,
    fine_voxel: float | None = None,
    views: tuple[AlignConfig, Scales] | None = None,
) -> tuple[list[PairResult], list[dict[int, np.ndarray]]]:
    """(results with one hypothesis chosen per pair within each set of scans placed
    together, those sets as {scan: pose in the set's frame}, the anchors' set first) --
    module docstring. ``anchors``: {scan: T_world_scan} taken as right; ``max_voxels``:
    the agreement tolerance, in feature voxels, on each scan's extent; ``views``: the
    settings and scales of the free-space tests each placement must pass against the
    placed scans (None: agreement alone)."""
    agreement = _Agreement(pre, hyp, max_voxels * voxel)
    check = None if views is None else _Views(pre, *views, agreement)
    overlap = {(r.i, r.j): float(r.overlap_ratio) for r in results}
    overlap.update({e: overlap.get(e, 0.0) for e in hyp})
    anchored = {int(s): np.asarray(T, dtype=np.float64) for s, T in anchors.items()}
    clusters: list[dict[int, np.ndarray]] = []
    taken: set[int] = set()
    while True:
        if anchored and not clusters:
            starts = [anchored]
        else:
            starts = _seeds(agreement, hyp, overlap, max_seeds, taken)
            if check is not None:  # a triangle whose views contradict each other: no start
                starts = [t for t in starts if check.coherent(t)]
        best, best_key = {}, (0, 0)
        for start in starts:
            grown = _grow(len(pre), start, agreement, overlap, min_agreeing, taken, check)
            if check is not None:  # only then can a scan hang on one pair
                grown = _on_cycles(grown, agreement, hyp, anchored, min_agreeing)
            key = (len(grown), len(_agreeing(grown, agreement, hyp)))
            if key > best_key:
                best, best_key = grown, key
        if not best:
            break
        clusters.append(best)
        taken |= set(best)
    out = _chosen(pre, results, hyp, clusters, agreement, fine_voxel or voxel / 2)
    return out, clusters


def _chosen(pre, results, hyp: Hypotheses, clusters, agreement: _Agreement, fine_voxel):
    """Each pair within a set of scans placed together with the hypothesis agreeing with
    their poses (or rejected when none does and it was accepted); every pair carries all
    its accepted hypotheses in ``stats["accepted_hypotheses"]`` (the model search tries them)."""
    where = {s: (k, T) for k, c in enumerate(clusters) for s, T in c.items()}
    out = []
    for r in results:
        i, j = r.i, r.j
        hs = hyp.get((i, j), [])
        if len(hs) > len(r.stats.get("accepted_hypotheses", [])):
            r = replace(r, stats={**r.stats, "accepted_hypotheses": [h for h in hs if h[1]]})
        if i not in where or j not in where or where[i][0] != where[j][0]:
            out.append(r)
            continue
        want = invert_transform(where[i][1]) @ where[j][1]
        match = next((h for h in hs if agreement.same(j, h[0], want)), None)
        if match is None:
            if r.accepted:
                reason = "none of its hypotheses agrees with the poses chosen jointly"
                r = replace(r, accepted=False, reason=reason)
            out.append(r)
        elif (np.allclose(match[0], r.T_i_j) and r.accepted) or match[1] is None:
            out.append(r)
        else:
            stats = {**r.stats, "joint_choice": True}
            start = time.perf_counter()
            out.append(
                pair_result(
                    pre[i],
                    pre[j],
                    i,
                    j,
                    match[0],
                    "",
                    match[1],
                    stats,
                    start,
                    fine_voxel=fine_voxel,
                )  # fmt: skip
            )
    return out


def choose_jointly(
    pre: Sequence[PreprocessedScan],
    results: Sequence[PairResult],
    todo: Sequence[int],
    anchors: dict[int, np.ndarray],
    cfg: AlignConfig,
    search: SearchConfig,
    executor: Executor | int,
    scales: Scales,
    max_voxels: float = 2.0,
) -> list[list[PairResult]]:
    """The second chance of the scans in ``todo`` (not verified by a first pass): each one's
    ``search.joint_partners`` candidate pairs nearest by global descriptor are searched
    (:func:`search_hypotheses`; every scan's nearest first, then the second...) and one
    hypothesis per pair is chosen jointly (:func:`joint_choice`) from ``anchors``
    ({scan: T_world_scan} verified), twice: on agreement alone, and with the views'
    free-space tests. For the second, where the choice leaves scans outside the first set
    (the anchors', else the largest), their candidate pairs with that set are searched the
    same way and the choice is made again: a set that grew in its own frame needs one right
    link to join (featuretype sparse seed 1: scans 6-9 right among themselves, none of
    their nearest pairs with the others right). At most ``search.joint_max_pairs`` pairs
    are searched in all. Returns both choices (results, the same objects where nothing
    changed); the pipeline runs a pass on each and keeps the one that verifies the most
    scans (neither choice is better on every run: docs/design/pairwise.md)."""
    from mvreg.pairwise.candidates import global_descriptor

    desc = np.stack([global_descriptor(p) for p in pre])
    budget = search.joint_max_pairs
    pairs = _nearest_pairs(todo, results, desc, search.joint_partners, budget)
    hyp = search_hypotheses(pre, results, pairs, cfg, search, executor, scales=scales)
    kw = {"max_voxels": max_voxels, "fine_voxel": scales.fine_voxel}
    plain = joint_choice(pre, results, hyp, anchors, scales.voxel, **kw)[0]
    kw["views"] = (cfg, scales)
    checked, sets = joint_choice(pre, results, hyp, anchors, scales.voxel, **kw)
    if not sets:
        return [plain, checked]
    rest = sorted((set(todo) | {s for c in sets[1:] for s in c}) - set(sets[0]))
    links = _nearest_pairs(
        rest, results, desc, search.joint_partners, budget - len(pairs),
        partners=set(sets[0]), exclude=set(pairs),
    )  # fmt: skip
    if links:
        hyp = search_hypotheses(pre, results, links, cfg, search, executor, scales=scales, hyp=hyp)
        checked = joint_choice(pre, results, hyp, anchors, scales.voxel, **kw)[0]
    return [plain, checked]


def _nearest_pairs(scans, results, desc, per_scan: int, limit: int, partners=None, exclude=()):
    """Up to ``limit`` candidate pairs of ``scans``: each scan's ``per_scan`` nearest by
    global descriptor (with a scan of ``partners`` only, when given; none of ``exclude``),
    every scan's nearest first, then the second..."""
    ranked = []  # per scan, its candidate pairs nearest by descriptor first
    for a in sorted(scans):
        mine = [
            (r.i, r.j)
            for r in results
            if a in (r.i, r.j)
            and (r.i, r.j) not in exclude
            and (partners is None or (r.j if r.i == a else r.i) in partners)
        ]
        other = np.array([j if i == a else i for i, j in mine], dtype=np.int64)
        order = np.argsort(np.linalg.norm(desc[other] - desc[a], axis=1), kind="stable")
        ranked.append([mine[k] for k in order[:per_scan]])
    pairs: list[tuple[int, int]] = []
    for rank in range(per_scan):
        for mine in ranked:
            if rank < len(mine) and mine[rank] not in pairs:
                pairs.append(mine[rank])
    return pairs[: max(0, limit)]
