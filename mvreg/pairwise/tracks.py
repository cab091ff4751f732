"""Stage 4: correspondences of accepted pairs -> tracks -> the patch problem.

Each accepted pair contributes mutual nearest neighbours between the two scans' fine
points (after alignment, within ``max_correspondence_voxels * v``, normals agreeing).
Union-find over all of them (connected components of the correspondence graph) gives
tracks: one physical point seen by several scans, one node of the
:class:`~mvreg.solver.problem.PatchProblem`. A track that sees a scan twice is
inconsistent (two points of one scan cannot be the same point). With many overlapping
scans such chains are common (mutual nearest neighbours of differently sampled surfaces
drift along a chain of scans; numbers in ``docs/design/pairwise.md``), so by default
(``split_conflicting_tracks``) a conflicting component is rebuilt greedily,
its links taken shortest first and a link refused when it would put two points of one
scan into a track (counted in ``num_refused_links``); otherwise it is dropped (counted in
``num_dropped_tracks``). Either way every track sees each scan at most once. Patches
are the scans (names = file names); a scan's
observations are its fine points at their local coordinates.

Pairs can be re-weighted later without new nearest-neighbour searches:
``tracks.reweighted(pair_weights)`` rebuilds the tracks from the stored correspondences,
leaving out pairs of weight 0; an observation's weight is the largest weight of the pairs
that link it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from mvreg.config.tracks import TracksConfig
from mvreg.executor import Executor, make_executor
from mvreg.geometry import transform_points
from mvreg.pairwise.correspondences import mutual_correspondences
from mvreg.pairwise.preprocess import PreprocessedScan, scan_scales
from mvreg.pairwise.result import PairResult
from mvreg.scales import Scales


@dataclass
class Tracks:
    """Tracks over all scans and the patch problem built from them.

    Observation arrays (length K, over all scans):
        obs_scan: scan index; obs_point: index into that scan's fine points;
        obs_node: track (node) id 0..num_tracks-1; coords: (K, 3) local coordinates;
        weight: (K,) observation weight; obs_pair: (K,) index into ``pairs`` of the first
        pair that linked the observation.
    Links (length L, one per kept correspondence): ``link_obs`` (L, 2) observation indices,
    ``link_pair`` (L,) pair index; they say exactly which pair joined which observations.
    Pairs (length P): ``pairs`` (P, 2) scan indices, ``pair_weights`` (P,),
    ``pair_num_correspondences`` (P,) before conflicts are resolved.
    Counts: ``num_conflicting_tracks`` components that saw a scan twice, of which
    ``num_dropped_tracks`` were dropped (drop mode) or split by refusing
    ``num_refused_links`` links (split mode); ``num_dropped_observations`` points that
    ended in no track of two or more.

    ``problem`` is the PatchProblem over the largest set of scans connected by tracks
    (patch p is scan ``patch_scans[p]``; its observations are ``problem_observations``
    of the arrays above); ``unconnected_scans`` names the scans left out. ``problem`` is
    None when no pair is linked. It is connected by construction; whether every patch
    shares d+1 independent nodes is left to the solver (``problem.check_local_rigidity()``).
    """

    scan_names: list[str]
    obs_scan: np.ndarray
    obs_point: np.ndarray
    obs_node: np.ndarray
    coords: np.ndarray
    weight: np.ndarray
    obs_pair: np.ndarray
    link_obs: np.ndarray
    link_pair: np.ndarray
    pairs: np.ndarray
    pair_weights: np.ndarray
    pair_num_correspondences: np.ndarray
    num_tracks: int
    num_conflicting_tracks: int
    num_dropped_tracks: int
    num_refused_links: int
    num_dropped_observations: int
    patch_scans: np.ndarray
    problem_observations: np.ndarray
    unconnected_scans: list[str]
    problem: object | None = field(default=None, repr=False)
    _inputs: tuple = field(default=(), repr=False, compare=False)

    @property
    def num_observations(self) -> int:
        return int(len(self.obs_scan))

    def __repr__(self) -> str:
        return (
            f"Tracks(scans={len(self.scan_names)}, pairs={len(self.pairs)}, "
            f"tracks={self.num_tracks}, observations={self.num_observations}, "
            f"conflicting={self.num_conflicting_tracks}, dropped={self.num_dropped_tracks}, "
            f"refused_links={self.num_refused_links}, unconnected={self.unconnected_scans})"
        )

    def reweighted(self, pair_weights: Sequence[float] | np.ndarray) -> Tracks:
        """Tracks rebuilt with new pair weights (0 leaves a pair out), same correspondences."""
        points, names, pairs, corr, _, distances, split = self._inputs
        return tracks_from_correspondences(
            points, names, pairs, corr, pair_weights, distances=distances, split_conflicts=split
        )


def pair_correspondences(
    pre_i: PreprocessedScan,
    pre_j: PreprocessedScan,
    T_i_j: np.ndarray,
    cfg: TracksConfig | None = None,
    *,
    scales: Scales | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Mutual correspondences between two scans' fine points -> (idx_i, idx_j).

    ``scales``: the run's (default: those ``pre_i`` was preprocessed at).
    """
    cfg = cfg or TracksConfig()
    scales = scan_scales(pre_i) if scales is None else scales
    idx_i, idx_j = mutual_correspondences(
        pre_i.fine_points,
        pre_j.fine_points,
        T_i_j,
        cfg.max_correspondence_voxels * scales.voxel,
        normals_i=pre_i.fine_normals,
        normals_j=pre_j.fine_normals,
        min_normal_cos=cfg.min_normal_cos,
        tree_i=pre_i.fine_tree(),
        tree_j=pre_j.fine_tree(),
    )
    n = cfg.max_correspondences_per_pair
    if n is not None and len(idx_i) > n:
        keep = np.linspace(0, len(idx_i) - 1, n).round().astype(np.int64)
        idx_i, idx_j = idx_i[keep], idx_j[keep]
    return idx_i, idx_j


def build_tracks(
    pre: Sequence[PreprocessedScan],
    results: Sequence[PairResult],
    cfg: TracksConfig | None = None,
    pair_weights: Sequence[float] | None = None,
    executor: Executor | int = 2,
    *,
    scales: Scales | None = None,
) -> Tracks:
    """Correspondences of the accepted pairs among ``results`` -> :class:`Tracks`.

    ``pair_weights`` (one per accepted result, default 1) weight the observations. The
    pairs are matched on ``executor`` (an int: that many threads; KD-tree queries release
    the GIL); the result does not depend on it. ``scales``: the run's (default: those
    each scan was preprocessed at).
    """
    cfg = cfg or TracksConfig()
    accepted = [r for r in results if r.accepted]

    def match(r):
        idx_i, idx_j = pair_correspondences(pre[r.i], pre[r.j], r.T_i_j, cfg, scales=scales)
        moved = transform_points(r.T_i_j, pre[r.j].fine_points[idx_j])
        return (idx_i, idx_j), np.linalg.norm(pre[r.i].fine_points[idx_i] - moved, axis=1)

    for r in accepted:  # build the KD-trees once, before the threads share them
        pre[r.i].fine_tree()
        pre[r.j].fine_tree()
    matched = make_executor(executor).map(match, accepted)
    corr = [m[0] for m in matched]
    distances = [m[1] for m in matched]
    pairs = np.array([(r.i, r.j) for r in accepted], dtype=np.int64).reshape(-1, 2)
    return tracks_from_correspondences(
        [p.fine_points for p in pre],
        [p.name for p in pre],
        pairs,
        corr,
        pair_weights,
        distances=distances,
        split_conflicts=cfg.split_conflicting_tracks,
    )


def tracks_from_correspondences(
    points: Sequence[np.ndarray],
    names: Sequence[str],
    pairs: np.ndarray,
    correspondences: Sequence[tuple[np.ndarray, np.ndarray]],
    pair_weights: Sequence[float] | np.ndarray | None = None,
    *,
    distances: Sequence[np.ndarray] | None = None,
    split_conflicts: bool = True,
) -> Tracks:
    """Union-find over point correspondences -> :class:`Tracks` (see the module docstring).

    Args:
        points: per scan, (N_s, 3) float64 local coordinates of the matchable points.
        names: per scan, its name (the patch name).
        pairs: (P, 2) scan indices (i, j) of each pair.
        correspondences: per pair, (idx_i, idx_j) point indices into points[i], points[j].
        pair_weights: (P,) >= 0, default 1; pairs of weight 0 are left out.
        distances: per pair, (C,) length of each correspondence (after alignment); sets
            the order in which links of a conflicting track are taken (default: as given).
        split_conflicts: split tracks that see a scan twice (True) or drop them.
    """
    m = len(points)
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    p_count = len(pairs)
    weights = np.ones(p_count) if pair_weights is None else np.asarray(pair_weights, float)
    if weights.shape != (p_count,):
        raise ValueError(f"{weights.shape[0]} pair weights for {p_count} pairs")
    offsets = np.concatenate([[0], np.cumsum([len(p) for p in points])]).astype(np.int64)
    counts = np.array([len(c[0]) for c in correspondences], dtype=np.int64)
    links = _links(pairs, correspondences, weights, counts, offsets, distances)
    g = _label_points(links, offsets, m, split_conflicts)
    obs = _observations(points, links[2], g, offsets, weights)
    patch_scans, problem_obs, problem = _largest_problem(obs, names, m)
    in_problem = set(patch_scans.tolist())
    return Tracks(
        scan_names=[str(n) for n in names],
        obs_scan=obs["obs_scan"],
        obs_point=obs["obs_point"],
        obs_node=obs["obs_node"],
        coords=obs["coords"],
        weight=obs["weight"],
        obs_pair=obs["obs_pair"],
        link_obs=obs["link_obs"],
        link_pair=obs["link_pair"],
        pairs=pairs,
        pair_weights=weights,
        pair_num_correspondences=counts,
        num_tracks=obs["num_tracks"],
        num_conflicting_tracks=g["num_conflicting"],
        num_dropped_tracks=0 if split_conflicts else g["num_conflicting"],
        num_refused_links=int(g["refused"]),
        num_dropped_observations=obs["num_dropped"],
        patch_scans=patch_scans,
        problem_observations=problem_obs,
        unconnected_scans=[str(names[s]) for s in range(m) if s not in in_problem],
        problem=problem,
        _inputs=(
            list(points), list(names), pairs, list(correspondences), weights,
            None if distances is None else list(distances), split_conflicts,
        ),
    )  # fmt: skip


def _links(pairs, correspondences, weights, counts, offsets, distances):
    """The correspondences of the pairs in use as links between global point ids:
    (a, b, pair of each link, length of each link)."""
    use = [k for k in range(len(pairs)) if weights[k] > 0 and counts[k] > 0]
    if not use:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    a = np.concatenate([offsets[pairs[k, 0]] + correspondences[k][0] for k in use])
    b = np.concatenate([offsets[pairs[k, 1]] + correspondences[k][1] for k in use])
    edge_pair = np.concatenate([np.full(counts[k], k, np.int64) for k in use])
    edge_len = (
        np.concatenate([np.asarray(distances[k], float) for k in use])
        if distances is not None
        else np.zeros(len(a))
    )
    return a, b, edge_pair, edge_len


def _label_points(links, offsets, m: int, split_conflicts: bool) -> dict:
    """Union-find as connected components of the graph on the linked points only; a
    component that sees a scan twice is split (or dropped: label -1)."""
    a, b, _, edge_len = links
    verts, inv = np.unique(np.concatenate([a, b]), return_inverse=True)
    ea, eb = inv[: len(a)], inv[len(a) :]
    nv = len(verts)
    if nv:
        graph = sp.coo_matrix((np.ones(len(ea)), (ea, eb)), shape=(nv, nv))
        num_labels, label = connected_components(graph, directed=False)
    else:
        num_labels, label = 0, np.zeros(0, np.int64)
    vert_scan = np.searchsorted(offsets, verts, side="right") - 1
    # A track seeing one scan twice: some (label, scan) occurs more than once.
    uniq, key_count = np.unique(label * m + vert_scan, return_counts=True)
    bad = np.zeros(num_labels, bool)
    bad[uniq[key_count > 1] // m] = True
    num_conflicting = int(bad.sum())
    refused = 0
    if num_conflicting and split_conflicts:
        label, refused = split_tracks(label, num_labels, bad, ea, eb, edge_len, vert_scan)
    elif num_conflicting:
        label = np.where(bad[label], -1, label)
    return {
        "verts": verts, "ea": ea, "eb": eb, "label": label, "vert_scan": vert_scan,
        "num_conflicting": num_conflicting, "refused": refused,
    }  # fmt: skip


def _observations(points, edge_pair, g: dict, offsets, weights) -> dict:
    """Tracks are the labels held by two or more points (ids in order of first point);
    observations are their points, in point-id order, with weights and first pairs."""
    verts, ea, eb, label = g["verts"], g["ea"], g["eb"], g["label"]
    nv = len(verts)
    size = np.bincount(label[label >= 0], minlength=1)
    keep_vert = label >= 0
    keep_vert[keep_vert] = size[label[keep_vert]] >= 2
    kept_labels, first_vert = np.unique(label[keep_vert], return_index=True)
    node_of_label = np.full(int(label.max()) + 1 if nv else 0, -1, np.int64)
    node_of_label[kept_labels[np.argsort(first_vert, kind="stable")]] = np.arange(len(kept_labels))
    obs_vert = np.flatnonzero(keep_vert)  # observations = kept points, in point-id order
    obs_of_vert = np.full(nv, -1, np.int64)
    obs_of_vert[obs_vert] = np.arange(len(obs_vert))
    obs_scan = g["vert_scan"][obs_vert]
    all_points = np.vstack([np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in points])
    link_keep = keep_vert[ea] & (label[ea] == label[eb])  # refused links join two tracks
    link_obs = np.stack([obs_of_vert[ea[link_keep]], obs_of_vert[eb[link_keep]]], axis=1)
    link_pair = edge_pair[link_keep]
    weight = np.zeros(len(obs_vert))
    for end in (0, 1):
        np.maximum.at(weight, link_obs[:, end], weights[link_pair])
    # The first link (lowest index) touching each observation names its pair.
    ends = link_obs.T.ravel()
    link_idx = np.tile(np.arange(len(link_obs)), 2)
    order = np.lexsort((link_idx, ends))
    _, first = np.unique(ends[order], return_index=True)
    return {
        "obs_scan": obs_scan,
        "obs_point": verts[obs_vert] - offsets[obs_scan],
        "obs_node": node_of_label[label[obs_vert]],
        "coords": all_points[verts[obs_vert]],
        "weight": weight,
        "obs_pair": link_pair[link_idx[order[first]]],
        "link_obs": link_obs,
        "link_pair": link_pair,
        "num_tracks": int(len(kept_labels)),
        "num_dropped": int(np.count_nonzero(~keep_vert)),
    }


def _largest_problem(obs: dict, names, m: int):
    """The largest set of scans connected through tracks and its PatchProblem:
    (patch_scans, problem_observations, problem or None)."""
    from mvreg.solver.problem import PatchProblem

    obs_scan, obs_node, num_tracks = obs["obs_scan"], obs["obs_node"], obs["num_tracks"]
    scan_graph = sp.coo_matrix(
        (np.ones(len(obs_scan)), (obs_scan, m + obs_node)),
        shape=(m + num_tracks, m + num_tracks),
    )
    _, comp = connected_components(scan_graph, directed=False)
    comp = comp[:m]
    seen = np.bincount(obs_scan, minlength=m) > 0
    if not seen.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64), None
    sizes = np.bincount(comp[seen], minlength=comp.max() + 1)
    best = int(np.argmax(sizes))  # ties: lowest label, i.e. the component of scan 0 first
    patch_scans = np.flatnonzero((comp == best) & seen)
    patch_of_scan = np.full(m, -1, np.int64)
    patch_of_scan[patch_scans] = np.arange(len(patch_scans))
    problem_obs = np.flatnonzero(patch_of_scan[obs_scan] >= 0)
    problem = PatchProblem(
        coords=obs["coords"][problem_obs],
        patch=patch_of_scan[obs_scan[problem_obs]],
        node=obs_node[problem_obs],
        weight=obs["weight"][problem_obs],
        patch_names=[str(names[s]) for s in patch_scans],
        check_well_posed=False,  # connected by construction; rigidity: the solver's job
    )
    return patch_scans, problem_obs, problem


def split_tracks(label, num_labels, bad, ea, eb, edge_len, vert_scan, batches=32):
    """Greedy union-find (shortest links first) inside the conflicting components.

    A link is refused when the two partial tracks already share a scan. Returns new labels
    (conflicting components get fresh ids >= num_labels) and the number of refused links.

    The links are taken in ``batches`` runs of increasing length, each settled mostly in
    arrays with the same result as one link at a time: a link between one partial track
    or two that share a scan at the start of a run is settled at once (scan sets only
    grow, so it would be refused whenever met), and the links of a run that join partial
    tracks into a set seeing every scan at most once all merge (none could be refused);
    only the links of runs' conflicting sets go one by one.
    """
    label = label.copy()
    verts = np.flatnonzero(bad[label])
    n = len(verts)
    local = np.full(len(label), -1, np.int64)
    local[verts] = np.arange(n)
    edges = np.flatnonzero(bad[label[ea]])
    edges = edges[np.argsort(edge_len[edges], kind="stable")]
    U, W = local[ea[edges]], local[eb[edges]]
    words = int(vert_scan.max()) // 64 + 1 if len(vert_scan) else 1
    s = vert_scan[verts].astype(np.int64)
    mask = np.zeros((n, words), np.uint64)  # scan set of each partial track (at its root)
    mask[np.arange(n), s // 64] = np.left_shift(np.uint64(1), (s % 64).astype(np.uint64))
    root = np.arange(n)
    refused = 0
    for run in np.array_split(np.arange(len(U)), max(1, min(batches, len(U)))):
        u, w = root[U[run]], root[W[run]]
        live = u != w
        clash = live & np.any(mask[u] & mask[w], axis=1)
        refused += int(np.count_nonzero(clash))
        live &= ~clash
        refused += _settle_run(u[live], w[live], root, mask)
        while True:  # full path compression
            nxt = root[root]
            if np.array_equal(nxt, root):
                break
            root = nxt
    label[verts] = num_labels + root
    return label, refused


def _settle_run(u, w, root, mask) -> int:
    """Merge along the links (u, w) between roots, in order (see :func:`split_tracks`);
    updates ``root`` and ``mask`` in place; returns the number of refused links."""
    if not len(u):
        return 0
    nodes, inv = np.unique(np.r_[u, w], return_inverse=True)
    cu, cw = inv[: len(u)], inv[len(u) :]
    shape = (len(nodes), len(nodes))
    k, comp = connected_components(sp.coo_matrix((np.ones(len(cu)), (cu, cw)), shape=shape))
    merged = np.zeros((k, mask.shape[1]), np.uint64)
    np.bitwise_or.at(merged, comp, mask[nodes])
    ones = np.bincount(comp, weights=np.bitwise_count(mask[nodes]).sum(axis=1), minlength=k)
    free = ones == np.bitwise_count(merged).sum(axis=1)  # disjoint scan sets
    first = np.full(k, np.iinfo(np.int64).max)
    np.minimum.at(first, comp, nodes)
    easy = free[comp]
    root[nodes[easy]] = first[comp[easy]]
    mask[first[free]] = merged[free]
    hard = ~free[comp[cu]]
    if not np.any(hard):
        return 0
    parent = {int(r): int(r) for r in nodes[~easy]}
    scans = {r: int.from_bytes(mask[r].tobytes(), "little") for r in parent}
    refused = 0
    for a, b in zip(u[hard].tolist(), w[hard].tolist(), strict=True):
        while parent[a] != a:
            parent[a] = a = parent[parent[a]]
        while parent[b] != b:
            parent[b] = b = parent[parent[b]]
        if a == b:
            continue
        if scans[a] & scans[b]:
            refused += 1
            continue
        if a > b:
            a, b = b, a
        parent[b] = a
        scans[a] |= scans[b]
    for r in parent:
        q = r
        while parent[q] != q:
            q = parent[q]
        root[r] = q
        if q == r:
            mask[r] = np.frombuffer(scans[r].to_bytes(8 * mask.shape[1], "little"), np.uint64)
    return refused
