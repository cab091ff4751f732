"""Point correspondences between two aligned scans: mutual nearest neighbours.

Used for the tracks (with a pairwise ``T_i_j``) and for multiview refinement (with
``T_i_j = inv(T_world_i) @ T_world_j`` from global poses).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from mvreg.geometry import invert_transform, transform_points


def mutual_correspondences(
    points_i: np.ndarray,
    points_j: np.ndarray,
    T_i_j: np.ndarray,
    max_dist: float,
    *,
    normals_i: np.ndarray | None = None,
    normals_j: np.ndarray | None = None,
    min_normal_cos: float | None = None,
    tree_i: cKDTree | None = None,
    tree_j: cKDTree | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Mutual nearest neighbours of two point sets after mapping j into i's frame.

    A pair (a, b) is kept when ``points_i[a]`` is the nearest point of scan i to
    ``T_i_j * points_j[b]``, that one is in turn nearest to it among scan j's points, their
    distance is at most ``max_dist``, and, when normals and ``min_normal_cos`` are given,
    the normals agree: ``n_i[a] . (R_i_j n_j[b]) >= min_normal_cos`` (this keeps the front
    of a thin part from matching its back).

    Args:
        points_i: (N_i, 3) float64, scan i's local frame.
        points_j: (N_j, 3) float64, scan j's local frame.
        T_i_j: (4, 4) maps scan j's points into scan i's frame.
        max_dist: largest accepted distance, data units.
        normals_i, normals_j: optional (N_i, 3), (N_j, 3) unit normals (local frames).
        min_normal_cos: optional cosine threshold for the normal test.
        tree_i, tree_j: optional ``cKDTree`` of ``points_i`` / ``points_j`` (untransformed),
            to reuse across calls.
    Returns:
        (idx_i, idx_j): (C,) int64 arrays, sorted by idx_j, indexing ``points_i`` / ``points_j``.
    """
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    if len(points_i) == 0 or len(points_j) == 0:
        return empty
    tree_i = tree_i if tree_i is not None else cKDTree(points_i)
    tree_j = tree_j if tree_j is not None else cKDTree(points_j)
    # Query each tree in its own frame so both trees can be built once and reused.
    d_ji, nn_ji = tree_i.query(transform_points(T_i_j, points_j), distance_upper_bound=max_dist)
    idx_j = np.flatnonzero(np.isfinite(d_ji))
    idx_i = nn_ji[idx_j]
    # The way back is needed only from the points of i that some point of j chose.
    hit = np.unique(idx_i)
    d_back, nn_back = tree_j.query(
        transform_points(invert_transform(T_i_j), points_i[hit]), distance_upper_bound=max_dist
    )
    back = np.searchsorted(hit, idx_i)
    mutual = np.isfinite(d_back[back]) & (nn_back[back] == idx_j)
    idx_i, idx_j = idx_i[mutual], idx_j[mutual]
    if min_normal_cos is not None and normals_i is not None and normals_j is not None:
        rotated = normals_j[idx_j] @ T_i_j[:3, :3].T
        ok = np.einsum("ij,ij->i", normals_i[idx_i], rotated) >= min_normal_cos
        idx_i, idx_j = idx_i[ok], idx_j[ok]
    if len(idx_i) == 0:
        return empty
    return idx_i.astype(np.int64), idx_j.astype(np.int64)
