"""Normals from neighbourhoods that span a surface.

Takes an Open3D point cloud and a radius; estimates its normals in place (PCA of the
neighbourhood within the radius, at most ``max_nn`` points). A normal is the direction of
least spread of the neighbourhood, which only a neighbourhood spread over two directions
fixes. A multi-beam LiDAR samples each ring densely and the rings far apart (data_synth's
32 beams: 0.13-0.26 m between rings at 6-12 m, against a fine voxel of 0.09 m): within two
fine voxels most points see only their own ring, a line, and the normal turns about it at
random (true poses of neighbouring stations read 8-10x the noise in residual; 2.5-4.6x
with the radius doubled, 1.3-1.8x tripled). So the radius grows through ``GROWTH`` x the
given one while more than ``MAX_LINEAR_SHARE`` of the neighbourhoods are lines (second
principal spread below ``LINE_RATIO`` of the first); scans sampled evenly across their
surface keep the given radius. Growth is asked for only where that sampling is known:
the fine level of a scan whose sensor its points surround (a spinning sensor;
:func:`~mvreg.pairwise.view_projection.surrounds`). Not for object views: there a line of
points is an edge-on strip of a thin part, and a wider radius mixes its two faces (grown
on every scan, the generalization benchmark registered 6 scans of ADIS16480 sparse seed 1,
5 of them verified 90-180 deg off; 0 registered without).
"""

from __future__ import annotations

import numpy as np

GROWTH = (1.0, 1.5, 2.0, 3.0, 4.0)
MAX_LINEAR_SHARE = 0.2
LINE_RATIO = 0.05  # variance ratio: the second axis spreads under ~22% of the first


def linear_share(pcd, radius: float, max_nn: int) -> float:
    """Share of the points whose neighbourhood (within ``radius``, at most ``max_nn``) is
    a line."""
    import open3d as o3d

    pcd.estimate_covariances(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))
    lam = np.linalg.eigvalsh(np.asarray(pcd.covariances))  # ascending
    return float(np.mean(lam[:, 1] < LINE_RATIO * np.maximum(lam[:, 2], 1e-300)))


def estimate_normals(pcd, radius: float, max_nn: int, grow: bool = False) -> float:
    """Normals of ``pcd`` in place; with ``grow``, from the smallest radius of ``GROWTH`` x
    ``radius`` whose neighbourhoods are mostly not lines (module docstring). Returns the
    radius used."""
    import open3d as o3d

    for factor in GROWTH if grow else (1.0,):
        r = factor * radius
        if not grow:
            break
        if len(pcd.points) < 3 or linear_share(pcd, r, max_nn) <= MAX_LINEAR_SHARE:
            break
    pcd.covariances = o3d.utility.Matrix3dVector()  # normals from the neighbours, as always
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=r, max_nn=max_nn))
    return r
