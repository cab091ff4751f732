"""Triples of matches drawn among pairwise-consistent matches (guided RANSAC sampling).

Plain RANSAC draws three matches at random: with an inlier share w a triple is all inliers
with probability w^3, so at w = 2% (FPFH of a smooth or low-poly scan against a model of
many scans) a few thousand draws almost never find one. Two true matches a, b agree on
what a rigid motion keeps: the distance between their points and the angles between their
normals and the line joining them. A random pair of matches agrees on these only by chance.
So the triples here are drawn on the compatibility graph of the matches: a at random, b
among the matches compatible with a, c among those compatible with both. For an inlier a
most of its compatible matches are inliers, so a triple is all inliers with probability
about w instead of w^3.

Contract (pure functions, no I/O): :func:`compatibility` takes the matched points and
normals (source and destination, (m, 3) each), the RANSAC inlier distance and the normal
tolerance in degrees, and returns the compatible pairs as CSR arrays (indptr, indices);
:func:`draw_triples` draws (B, 3) index triples from them with a seeded generator.
Tolerances are the RANSAC acceptance rule's (``AlignConfig.ransac_distance_voxels``,
``ransac_normal_angle_deg``): every pair of matches that a hypothesis counts as inliers
and whose normals it accepts is compatible, up to the noise those tolerances allow.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.distance import cdist


def compatibility(
    src: np.ndarray,
    dst: np.ndarray,
    src_n: np.ndarray,
    dst_n: np.ndarray,
    dist: float,
    normal_deg: float,
    min_length: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of matches (a, b), a != b, that a rigid motion can map both ways: edge
    lengths within 2 ``dist`` of each other and above ``min_length``; the angle between
    the two normals, and each normal's angle with the edge, the same in both scans within
    ``normal_deg`` (the edge's direction also within what 2 ``dist`` allows).
    Returns (indptr (m + 1,), indices) of the symmetric compatibility graph, rows sorted."""
    m = len(src)
    ls, ld = cdist(src, src), cdist(dst, dst)
    ok = (np.abs(ls - ld) <= 2.0 * dist) & (ls > min_length) & (ld > min_length)
    a, b = np.nonzero(np.triu(ok, 1))  # the normal tests on these pairs only
    tol = np.radians(normal_deg)  # |cos x - cos y| <= |x - y|
    keep = np.abs(np.sum(src_n[a] * src_n[b], 1) - np.sum(dst_n[a] * dst_n[b], 1)) <= tol
    a, b = a[keep], b[keep]
    es, ed = src[b] - src[a], dst[b] - dst[a]
    us, ud = ls[a, b], ld[a, b]
    edge_tol = tol + 2.0 * dist / np.minimum(us, ud)
    for end in (0, 1):  # each end's normal against the edge
        k = a if end == 0 else b
        cs = np.sum(src_n[k] * es, 1) / us
        cd = np.sum(dst_n[k] * ed, 1) / ud
        keep = np.abs(cs - cd) <= edge_tol
        a, b, es, ed, us, ud, edge_tol = (x[keep] for x in (a, b, es, ed, us, ud, edge_tol))
    rows, cols = np.r_[a, b], np.r_[b, a]
    order = np.lexsort((cols, rows))
    rows, cols = rows[order], cols[order]
    indptr = np.searchsorted(rows, np.arange(m + 1))
    return indptr.astype(np.int64), cols.astype(np.int64)


def draw_triples(
    rng: np.random.Generator, indptr: np.ndarray, indices: np.ndarray, batch: int
) -> np.ndarray:
    """(<= batch, 3) triples (a, b, c), pairwise compatible: a uniform among the matches
    with a compatible partner, b uniform among a's partners, c uniform among a's partners
    and kept when it is b's too."""
    deg = np.diff(indptr)
    starts = np.flatnonzero(deg >= 2)
    if len(starts) == 0:
        return np.zeros((0, 3), np.int64)
    a = starts[rng.integers(0, len(starts), batch)]
    b = indices[indptr[a] + (rng.random(batch) * deg[a]).astype(np.int64)]
    c = indices[indptr[a] + (rng.random(batch) * deg[a]).astype(np.int64)]
    keep = (b != c) & _adjacent(indptr, indices, b, c)
    return np.stack([a[keep], b[keep], c[keep]], axis=1)


def _adjacent(indptr: np.ndarray, indices: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Whether c[k] is in b[k]'s (sorted) partner list, for every k."""
    lo, hi = indptr[b], indptr[b + 1]
    # binary search of c in indices[lo:hi], vectorized over k
    while True:
        active = lo < hi
        if not np.any(active):
            break
        mid = (lo + hi) // 2
        val = np.where(active, indices[np.minimum(mid, len(indices) - 1)], 0)
        go_right = active & (val < c)
        lo = np.where(go_right, mid + 1, lo)
        hi = np.where(active & ~go_right, mid, hi)
    found = lo < indptr[b + 1]
    return found & (indices[np.minimum(lo, len(indices) - 1)] == c)
