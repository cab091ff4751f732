"""Where a single-view scan was seen from: the sensor position, when the data shows it.

Takes a scan's raw points (its own frame) and the view axis of
:func:`~mvreg.pairwise.preprocess.view_direction`; returns the sensor position in the
scan's frame, or None (then the view tests keep the orthographic approximation along the
axis). Pure function of the arrays; deterministic.

Why: the view tests of :mod:`mvreg.pairwise.scoring` ask what a view should have seen.
Seen along one axis (orthographic), a close-range scan of a part with steps, legs or
flanges looks wrong even under its true pose: a point the sensor saw past the edge of a
flange lies, along the axis, behind the flange, and a surface hidden by a leg from the
sensor lies, along the axis, where the view saw nothing. On synthetic scans at 1.5
object diagonals with a 55 deg field of view, the true poses of 24 of 26 overlapping
pairs of a chair failed the orthographic tests; seen from the true sensor positions,
16 passed (``docs/design/pairwise.md``).

How: a range scanner samples a regular grid of directions from its sensor (a camera's
pixels, a laser scanner's angular steps), and its noise is along the rays. Seen from the
true sensor position the directions to the points are that grid: the angular distance
from a point to its nearest neighbour is nearly the same within a patch. Seen from
anywhere else, it varies with the depth and slope of the surface. The estimate minimises
the spread of those gaps (interquartile range of their logarithm, each patch's relative
to its own median: a pinhole's pitch varies slowly across its image) over the sensor
position: on ``PATCHES`` patches of neighbouring raw points (the grid survives only
there), the nearest neighbour in direction taken among the ``NEIGHBOURS`` nearest in
space; ``DIRECTIONS`` x ``DISTANCES`` positions around the centroid, then Nelder-Mead
from the ``STARTS`` best. It is kept only when the grid it reveals is clearly more
regular than the points seen along its direction (spread at most ``max_spread_ratio`` of
the orthographic one, and at most ``MAX_SPREAD``) and the sensor is near enough for
perspective to matter (``MAX_DISTANCE_RADII``): a scan that was resampled, merged, made
by a sensor without a grid or from far away keeps the orthographic view; so does one
already a regular grid along its view axis (not searched).
A sensor position stored in the file is used as it is, without an estimate. The scan's
own frame origin is tried first (raw scans are usually written in the scanner's frame):
when the grid seen from it passes the same tests, it is taken without a search.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from mvreg.pairwise.nelder_mead import minimize_together

PATCHES = 6
PATCH_POINTS = 160
NEIGHBOURS = 6  # a point's nearest neighbour in direction is among its nearest in space
DISTANCES = (1.5, 2.2, 3.2, 4.6, 6.6, 9.5, 14.0)  # x rms radius
CHUNK = 64  # sensor positions scored at once


def _spread_of(gaps: np.ndarray) -> np.ndarray:
    """(..., patches, q) gaps -> (...,) interquartile range of the log gaps, each patch's
    relative to its median (a grid's spacing is regular locally; a pinhole's varies slowly
    across its image)."""
    logd = np.log(np.maximum(gaps, 1e-300))
    logd = logd - median_last_axis(logd)[..., None]
    q1, q3 = quartiles_last_axis(logd.reshape(*logd.shape[:-2], -1))
    return q3 - q1


# The sensor search evaluates _spread_of some 400 times per scan on small arrays, where
# np.median and np.percentile cost more in their generality than the arithmetic. These two
# do what they do for a float array without NaNs along the last axis, value for value:
# the same order statistics (np.partition), the same mean of the two middle ones, the same
# linear interpolation (numpy's _lerp); tests/test_viewpoint.py compares them bit for bit.
def median_last_axis(a: np.ndarray) -> np.ndarray:
    """``np.median(a, axis=-1)``."""
    n = a.shape[-1]
    h = n // 2
    if n % 2:
        return np.partition(a, h, axis=-1)[..., h]
    part = np.partition(a, [h - 1, h], axis=-1)
    return (part[..., h - 1] + part[..., h]) / 2.0


def quartiles_last_axis(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.percentile(a, [25, 75], axis=-1)`` (method "linear"), for 2 or more values."""
    n = a.shape[-1]
    virtual = (n - 1) * np.array([0.25, 0.75])
    below = np.floor(virtual)
    gamma = virtual - below
    lo = below.astype(np.intp)
    part = np.partition(a, np.unique(np.r_[lo, lo + 1]), axis=-1)
    x, y = part[..., lo], part[..., lo + 1]
    diff = y - x
    out = np.where(gamma >= 0.5, y - diff * (1 - gamma), x + diff * gamma)
    return out[..., 0], out[..., 1]


def _spreads(queries: np.ndarray, near: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Spread (:func:`_spread_of`) of the angular gaps from each query point to its nearest
    neighbour in direction, seen from each of ``centres`` (C, 3): ``queries`` (P, q, 3),
    ``near`` (P, q, K, 3) their nearest points in space."""
    out = np.empty(len(centres))
    for lo in range(0, len(centres), CHUNK):
        c = centres[lo : lo + CHUNK, None, None, :]
        uq = queries[None] - c
        uq /= np.sqrt(np.einsum("...i,...i->...", uq, uq))[..., None]
        un = near[None] - c[:, :, :, None, :]
        un /= np.sqrt(np.einsum("...i,...i->...", un, un))[..., None]
        diff = un - uq[..., None, :]
        gaps = np.sqrt(np.einsum("...i,...i->...", diff, diff).min(axis=-1))
        out[lo : lo + CHUNK] = _spread_of(gaps)
    return out


def _patches(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(queries (P, q, 3), near (P, q, K, 3)): in ``PATCHES`` neighbourhoods of
    ``PATCH_POINTS`` raw points seeded evenly through the scan, the inner half of each, and
    the ``NEIGHBOURS`` nearest other points of each of those."""
    n = len(points)
    k = min(PATCH_POINTS, max(20, n // PATCHES))
    tree = cKDTree(points)
    seeds = points[np.linspace(0, n - 1, PATCHES + 2).astype(int)[1:-1]]
    _, idx = tree.query(seeds, k=k)
    inner = np.atleast_2d(idx)[:, : k // 2]
    _, nb = tree.query(points[inner.ravel()], k=NEIGHBOURS + 1)
    near = points[nb[:, 1:]].reshape(*inner.shape, NEIGHBOURS, 3)
    return points[inner], near


def _sphere(n: int) -> np.ndarray:
    """``n`` nearly uniform unit vectors (Fibonacci sphere)."""
    i = np.arange(n) + 0.5
    polar, azimuth = np.arccos(1.0 - 2.0 * i / n), np.pi * (1.0 + 5**0.5) * i
    return np.stack(
        [np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], 1
    )


DIRECTIONS = _sphere(120)
STARTS = 4  # Nelder-Mead refinements, from the best grid positions
MAX_SPREAD = 0.015  # a sensor's grid: local spacings alike to 1.5% (interquartile range)
# The frame origin, one candidate given beforehand, needs less than the best of a search over
# hundreds: a spinning LiDAR's rings at different elevations space their points by
# cos(elevation), 0.004-0.016 of spread seen from its true position (data_synth's 32 beams).
ORIGIN_MAX_SPREAD = 2.0 * MAX_SPREAD
# Further than this many rms radii the rays to the scan are within about 3 deg of parallel:
# the orthographic view is as good, and which side the sensor is on is no longer told by the
# directions (seen from far behind, they are as regular).
MAX_DISTANCE_RADII = 20.0


def _tangents(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    return a, np.cross(d, a)


def _orthographic_spread(queries, near, d) -> float:
    a, b = _tangents(d)
    F = np.stack([a, b], 1)  # seen along d: the gaps across it
    return float(
        _spread_of(np.linalg.norm(near @ F - (queries @ F)[..., None, :], axis=-1).min(axis=-1))
    )


def estimate_viewpoint(
    points: np.ndarray, max_spread_ratio: float = 0.3, axis: np.ndarray | None = None
) -> tuple[np.ndarray | None, dict]:
    """(sensor position or None, stats) for a single-view scan (module docstring).

    ``points``: (N, 3) raw points in the scan's frame; ``axis``: the view axis when known
    (either sign): when the points seen along it are already a regular grid (spread at
    most ``MAX_SPREAD``), the sensor is far and the view orthographic (None, no search).
    Searched over ``DIRECTIONS`` from
    the centroid at ``DISTANCES`` rms radii, then refined by Nelder-Mead from the ``STARTS``
    best. stats: ``spread`` at the estimate, ``orthographic_spread`` seen along the
    direction of the estimate, ``distance_radii`` of the estimate from the centroid.
    """
    points = np.unique(np.asarray(points, dtype=np.float64), axis=0)  # no zero gaps
    if len(points) < 200:
        return None, {"reason": "too few points"}
    queries, near = _patches(points)
    if axis is not None and _orthographic_spread(queries, near, axis) <= MAX_SPREAD:
        return None, {"reason": "a regular grid seen along the axis: orthographic"}
    m = points.mean(0)
    flat = queries.reshape(-1, 3)
    radius = float(np.sqrt(np.mean(np.sum((flat - m) ** 2, axis=1))))
    origin = np.zeros(3)
    if np.min(np.linalg.norm(flat, axis=1)) > 0.05 * radius:  # the frame's own origin first
        stats = _judge(origin, float(_spreads(queries, near, origin[None])[0]), queries, near, m,
                       radius, max_spread_ratio, ORIGIN_MAX_SPREAD)  # fmt: skip
        if stats["accepted"]:
            return origin, {**stats, "origin": True}

    def spread_from(centres):
        centres = np.atleast_2d(centres)
        inside = np.concatenate(
            [
                np.linalg.norm(flat[None] - centres[lo : lo + CHUNK, None], axis=2).min(axis=1)
                <= 0.05 * radius
                for lo in range(0, len(centres), CHUNK)
            ]
        )
        out = np.full(len(centres), np.inf)
        if not inside.all():
            out[~inside] = _spreads(queries, near, centres[~inside])
        return out

    grid = [(d, f) for d in DIRECTIONS for f in DISTANCES]
    values = spread_from(np.array([m + f * radius * d for d, f in grid]))
    starts = []
    for i in np.argsort(values, kind="stable")[:STARTS]:
        if not np.isfinite(values[i]):
            break
        d0, f0 = grid[i]
        starts.append((d0, *_tangents(d0), np.array([np.log(f0), 0.0, 0.0])))

    def centre(k, x):
        d0, a, b, _ = starts[k]
        dist = radius * np.exp(x[0])
        return m + dist * (d0 + x[1] * a + x[2] * b)

    # The starts refined together (mvreg.pairwise.nelder_mead: as scipy's Nelder-Mead one
    # after the other, in a quarter of the calls).
    found = minimize_together(
        lambda asked: spread_from(np.array([centre(k, x) for k, x in asked])),
        [np.vstack([x0, x0 + [0.2, 0, 0], x0 + [0, 0.08, 0], x0 + [0, 0, 0.08]])
         for *_, x0 in starts],
        xatol=1e-3, fatol=1e-4, maxfev=120,
    )  # fmt: skip
    res, best_c = None, None
    for k, (x, fun) in enumerate(found):
        if res is None or fun < res:
            res, best_c = fun, centre(k, x)
    if res is None:
        return None, {"reason": "no sensor position outside the points"}
    stats = _judge(best_c, float(res), queries, near, m, radius, max_spread_ratio)
    return (best_c if stats["accepted"] else None), stats


def _judge(c, spread, queries, near, m, radius, max_spread_ratio, limit=MAX_SPREAD) -> dict:
    """Stats of a candidate sensor position ``c`` whose grid has ``spread``, and whether it
    is kept: spread at most ``max_spread_ratio`` of the orthographic one seen along its
    direction and at most ``limit``, within ``MAX_DISTANCE_RADII``."""
    offset = c - m
    dist = float(np.linalg.norm(offset))
    axis = offset / dist if dist > 1e-12 * radius else np.array([0.0, 0.0, 1.0])
    ortho = _orthographic_spread(queries, near, axis)
    return {
        "spread": spread,
        "orthographic_spread": ortho,
        "distance_radii": dist / radius,
        "accepted": bool(
            spread <= min(max_spread_ratio * ortho, limit) and dist / radius <= MAX_DISTANCE_RADII
        ),
    }
