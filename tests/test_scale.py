"""Issue 14: the refinement's pairs grow with the scans, not with their square."""

from collections import Counter
from types import SimpleNamespace

import numpy as np

from bench.scale import fit_exponent
from mvreg.geometry import transform_points
from mvreg.globalstage.refine import overlapping_pairs


def _boxes_overlap(pre, T, margin):
    """Every pair whose grown world bounding boxes overlap, pair by pair."""
    boxes = {}
    for s, M in T.items():
        w = transform_points(M, pre[s].points)
        boxes[s] = (w.min(0) - margin, w.max(0) + margin)
    keys = sorted(boxes)
    return [
        (i, j)
        for a, i in enumerate(keys)
        for j in keys[a + 1 :]
        if np.all(np.maximum(boxes[i][0], boxes[j][0]) < np.minimum(boxes[i][1], boxes[j][1]))
    ]


def _ring(n, seed=0):
    """n patches of a circle's surface, each overlapping its neighbours along it."""
    rng = np.random.default_rng(seed)
    pre = []
    for k in range(n):
        a = rng.uniform(0, 0.6, 400) + 2 * np.pi * k / n
        pts = np.c_[np.cos(a), np.sin(a), rng.uniform(0, 0.1, 400)] * 10
        pre.append(SimpleNamespace(points=pts))
    return pre, {k: np.eye(4) for k in range(n)}


def test_uncapped_is_every_overlapping_box():
    pre, T = _ring(30)
    del T[4]  # an unregistered scan takes part in no pair
    for margin in (0.0, 0.1, 1.0, 5.0):
        assert overlapping_pairs(pre, T, margin, None) == _boxes_overlap(pre, T, margin)


def test_capped_pairs_are_bounded_and_keep_neighbours():
    pre, T = _ring(60)
    full = overlapping_pairs(pre, T, 0.2, None)
    capped = overlapping_pairs(pre, T, 0.2, 4)
    assert set(capped) <= set(full) and capped == sorted(capped)
    assert len(capped) <= 4 * 60 < len(full)
    degree = Counter(s for p in capped for s in p)
    assert min(degree[s] for s in range(60)) >= 4
    # neighbours along the ring share the most surface: each keeps both of them
    assert all((k, k + 1) in capped for k in range(59))


def test_few_partners_change_nothing():
    pre, T = _ring(10)
    assert overlapping_pairs(pre, T, 1.0, 12) == overlapping_pairs(pre, T, 1.0, None)


def test_fit_exponent():
    n = np.array([20, 40, 80, 160])
    assert abs(fit_exponent(n, 3.0 * n**1.5) - 1.5) < 1e-9
    assert fit_exponent([20], [1.0]) is None


def _pair_residuals_reference(tracks, T):
    """pair_residuals as it was: a mask per scan and per pair."""
    out = np.full(len(tracks.pairs), np.nan)
    a, b = tracks.link_obs[:, 0], tracks.link_obs[:, 1]
    sa, sb = tracks.obs_scan[a], tracks.obs_scan[b]
    ok = np.array([int(x) in T and int(y) in T for x, y in zip(sa, sb, strict=True)])
    pa, pb = np.empty((len(a), 3)), np.empty((len(a), 3))
    for s in np.unique(np.r_[sa[ok], sb[ok]]):
        ma, mb = ok & (sa == s), ok & (sb == s)
        pa[ma] = transform_points(T[int(s)], tracks.coords[a[ma]])
        pb[mb] = transform_points(T[int(s)], tracks.coords[b[mb]])
    dist = np.linalg.norm(pa - pb, axis=1)
    for p in np.unique(tracks.link_pair[ok]):
        out[p] = float(np.median(dist[ok & (tracks.link_pair == p)]))
    return out


def test_pair_residuals_same_as_per_pair_masks():
    from mvreg.geometry import random_rotations
    from mvreg.globalstage.robust import pair_residuals

    rng = np.random.default_rng(1)
    n, k, links = 12, 3000, 5000
    obs_scan = rng.integers(0, n, k)
    link_obs = rng.integers(0, k, (links, 2))
    tracks = SimpleNamespace(
        pairs=np.zeros((40, 2)),
        link_obs=link_obs,
        obs_scan=obs_scan,
        coords=rng.normal(size=(k, 3)),
        link_pair=rng.integers(0, 37, links),
    )
    R = random_rotations(rng, n)
    T = {s: np.r_[np.c_[R[s], rng.normal(size=3)], [[0, 0, 0, 1]]] for s in range(n) if s != 3}
    assert np.array_equal(
        pair_residuals(tracks, T), _pair_residuals_reference(tracks, T), equal_nan=True
    )


def test_overlap_residual_equals_the_query_of_every_other_scan():
    """One union tree with growing k gives the same figures as querying every other
    scan's tree (the per-scan loop it replaced: M^2 queries), including a scan far from
    all others within reach (k must grow past all its own points)."""
    from scipy.spatial import cKDTree

    from mvreg.metrics import overlap_residual, residual_summary

    rng = np.random.default_rng(0)
    pts = [rng.normal(size=(1500, 3)) * (1 + 0.1 * i) + 0.05 * i for i in range(8)]
    pts.append(rng.normal(size=(40, 3)) + 30.0)
    for max_d in (0.05, 0.3, 100.0):
        trees = [cKDTree(p) for p in pts]
        sample = np.random.default_rng(0)
        best_all = []
        for i, p in enumerate(pts):
            q = p if len(p) <= 1000 else p[sample.choice(len(p), 1000, replace=False)]
            best = np.full(len(q), np.inf)
            for j, t in enumerate(trees):
                if j != i:
                    best = np.minimum(best, t.query(q, distance_upper_bound=max_d)[0])
            best_all.append(best)
        ref = residual_summary(
            [b[b < max_d] for b in best_all],
            sum(len(b) for b in best_all),
            [float(np.median(b[b < max_d])) if np.any(b < max_d) else None for b in best_all],
            max_d,
        )
        assert overlap_residual(pts, max_d, max_points=1000) == ref
