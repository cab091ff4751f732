"""How a single view saw space: the projection the view tests of
:mod:`mvreg.pairwise.scoring` use.

Takes a scan's view direction, its sensor position (or None) and its fine points; returns
a :class:`ViewProjection` that maps points with normals to (lateral coordinates, depth,
cosine towards the sensor, whether the sensor could have seen them). Three kinds:

* orthographic (no sensor position): along the view direction ``d``; lateral = the
  coordinates across it, depth = p . d;
* perspective (a sensor whose points all lie within ``PERSPECTIVE_MAX_DEG`` of its axis,
  a camera or a scanner looking at an object): lateral on the image plane through the
  scan's centroid, depth = -range;
* spherical (a sensor with points all around it, a spinning LiDAR or a terrestrial laser
  scanner): lateral = the unit direction from the sensor (3 coordinates, no seam and no
  pole) times the scan's median range, depth = -range. Such a sensor sees only up to its
  range and within its field of view: :meth:`ViewProjection.could_see` is False for
  points farther than the farthest point it measured and for directions where it
  measured nothing within a few degrees (``COVER_RAD``: below a LiDAR's lowest beam, the
  blind cone under the sensor), so the unseen-space test does not count them.

Lateral units are lengths at the scan's depth (its centroid's, or the median range).
"""

from __future__ import annotations

import numpy as np

PERSPECTIVE_MAX_DEG = 70.0
"""A view whose points reach farther than this from its axis (99th percentile) is
spherical: a pinhole image plane cannot hold it."""

COVER_RAD = 0.05
"""Side (radians, about 3 deg) of the direction cells a spherical view's field of view is
judged on: a direction counts as inside it when a cell within one of it holds a point."""


def cell_keys(lateral: np.ndarray, cell: float) -> np.ndarray:
    """One int64 key per point: its cell of a grid of side ``cell`` over the (n, 2) or
    (n, 3) lateral coordinates."""
    idx = np.floor(lateral / cell).astype(np.int64)
    if idx.shape[1] == 2:
        return (idx[:, 0] << 32) + idx[:, 1]  # exact for |u|, |w| < 2**31 cells
    idx += 1 << 20  # 21 bits each: exact for |u|, |w|, |z| < 2**20 cells
    return (idx[:, 0] << 42) + (idx[:, 1] << 21) + idx[:, 2]


_STEPS = np.array(
    [(a << 42) + (b << 21) + c for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)],
    dtype=np.int64,
)


def neighbour_keys(keys: np.ndarray) -> np.ndarray:
    """(n, 27): the 3-d cell keys (:func:`cell_keys`) of each cell and its 26 neighbours."""
    return keys[:, None] + _STEPS[None]


def _dilated(keys: np.ndarray) -> np.ndarray:
    """Sorted unique 3-d cell keys of ``keys`` and their 26 neighbours."""
    return np.unique(neighbour_keys(np.unique(keys)).ravel())


def one_per_cell(points: np.ndarray, cell: float) -> np.ndarray:
    """The first finite point of each cell of side ``cell`` (in input order)."""
    points = points[np.all(np.isfinite(points), axis=1)]
    _, first = np.unique(np.floor(points / cell).astype(np.int64), axis=0, return_index=True)
    return points[np.sort(first)]


def towards(normals: np.ndarray, points: np.ndarray, sensor: np.ndarray) -> np.ndarray:
    """``normals`` with each sign turned to face ``sensor`` from its point."""
    return (
        normals * np.where(np.einsum("ij,ij->i", normals, sensor - points) < 0, -1.0, 1.0)[:, None]
    )


def set_viewpoint(out, seen_from: np.ndarray, normals: np.ndarray) -> None:
    """Make ``out`` a single view seen from ``seen_from`` (its frame): viewpoint, view
    direction (from the centroid of its fine points towards the sensor; +z for a sensor at
    that centroid) and the share of ``normals`` facing it."""
    direction = seen_from - out.fine_points.mean(0)
    length = np.linalg.norm(direction)  # 0 for a sensor at the centroid of a surround scan
    tiny = 1e-9 * out.fine_voxel_size
    direction = direction / length if length > tiny else np.array([0.0, 0.0, 1.0])
    out.view_facing = float(np.mean(normals @ direction > 0.05))
    out.view_direction, out.viewpoint = direction, np.asarray(seen_from, float).copy()


def surrounds(points: np.ndarray, c: np.ndarray, d: np.ndarray | None = None) -> bool:
    """Whether the points lie around the sensor at ``c`` rather than before it: the 99th
    percentile of their angle from the axis ``-d`` (``d``: unit direction from the points
    towards the sensor; default from their centroid) beyond ``PERSPECTIVE_MAX_DEG``."""
    rays = points - c
    if d is None:
        d = c - points.mean(0)
        length = np.linalg.norm(d)
        if length <= 0:
            return True
        d = d / length
    r = np.maximum(np.linalg.norm(rays, axis=1), 1e-300)
    off_axis = np.degrees(np.arccos(np.clip(-(rays @ d) / r, -1.0, 1.0)))
    return bool(np.percentile(off_axis, 99) > PERSPECTIVE_MAX_DEG)


class ViewProjection:
    """How a single view saw space (module docstring). ``d``: unit direction from the
    scan's centroid towards its sensor; ``c``: the sensor position or None
    (orthographic); ``points``: the scan's fine points (decide perspective or spherical,
    and a spherical view's range and field of view)."""

    def __init__(self, d: np.ndarray, c: np.ndarray | None, points: np.ndarray):
        self.d = np.asarray(d, dtype=np.float64)
        a = np.cross(self.d, [1.0, 0.0, 0.0] if abs(self.d[0]) < 0.9 else [0.0, 1.0, 0.0])
        a /= np.linalg.norm(a)
        self.F = np.stack([a, np.cross(self.d, a)])
        self.c = None if c is None else np.asarray(c, dtype=np.float64)
        centroid = points.mean(0)
        self.focal = None if c is None else float((self.c - centroid) @ self.d)
        self.spherical = False
        if self.c is None:
            return
        if not surrounds(points, self.c, self.d):
            return
        rays = points - self.c
        r = np.linalg.norm(rays, axis=1)
        self.spherical = True
        self.radius = float(np.median(r))
        self.max_range = float(r.max())
        self._cover = _dilated(cell_keys(rays / np.maximum(r, 1e-300)[:, None], COVER_RAD))

    def project(self, points: np.ndarray, normals: np.ndarray):
        """(lateral (n, 2) or (n, 3), depth (n,), cosine of normal and sensor direction
        (n,), in front of the sensor (n,) bool) of ``points`` in the scan's frame."""
        if self.c is None:
            return points @ self.F.T, points @ self.d, normals @ self.d, np.ones(len(points), bool)
        q = self.c - points
        r = np.linalg.norm(q, axis=1)
        cos = np.einsum("ij,ij->i", normals, q) / np.maximum(r, 1e-300)
        if self.spherical:
            lateral = q * (-self.radius / np.maximum(r, 1e-300))[:, None]
            return lateral, -r, cos, np.ones(len(points), bool)
        z = q @ self.d
        ahead = z > 1e-9 * max(self.focal, 1e-300)
        lateral = (-q @ self.F.T) * (self.focal / np.where(ahead, z, 1.0))[:, None]
        return lateral, -r, cos, ahead

    def lateral_scale(self, depth: np.ndarray) -> np.ndarray | float:
        """Length at a point's own depth of one lateral unit (1 but for a spherical view,
        whose lateral units are lengths at its median range)."""
        return -depth / self.radius if self.spherical else 1.0

    def could_see(self, lateral: np.ndarray, depth: np.ndarray) -> np.ndarray | bool:
        """Whether the sensor could have measured points there: True but for a spherical
        view, whose range and field of view are those of its points (module docstring)."""
        if not self.spherical:
            return True
        keys = cell_keys(lateral / self.radius, COVER_RAD)
        pos = np.minimum(np.searchsorted(self._cover, keys), len(self._cover) - 1)
        return (self._cover[pos] == keys) & (-depth <= self.max_range)
