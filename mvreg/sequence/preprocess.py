"""Preprocessing of range scans: the voxel levels of ``register`` with every normal
turned towards the sensor (a LiDAR scan is many disconnected pieces, where tangent-plane
propagation fails) and estimated from the nearest points of a ring.
"""

from __future__ import annotations

import numpy as np

from mvreg.config.preprocess import PreprocessConfig
from mvreg.config.sequence import SequenceConfig
from mvreg.errors import ConfigError
from mvreg.executor import single_threaded_blas
from mvreg.io.loaders import Scan
from mvreg.pairwise.preprocess import (
    PreprocessedScan,
    check_voxel_size,
    outlier_mask,
    plane_noise,
)
from mvreg.pairwise.view_projection import one_per_cell, set_viewpoint


def preprocess_range_scan(
    scan: Scan,
    voxel_size: float,
    cfg: PreprocessConfig | None = None,
    seq: SequenceConfig | None = None,
) -> PreprocessedScan:
    """Downsample a range scan and orient every normal towards its sensor (the origin).

    Like :func:`mvreg.pairwise.preprocess.preprocess` (same levels, outlier removal and
    noise estimate) except for the normals: a range scan sees every surface from the
    sensor, so each normal is turned to face it, which is exact where the tangent-plane
    propagation of ``preprocess`` fails (a LiDAR scan is many disconnected pieces). With
    ``seq.view_tests`` the scan is a view seen from its sensor (``viewpoint``; spherical
    when its points surround it), so pairs and verification run the free-space tests.
    FPFH features are computed on demand by :func:`ensure_features` (only the feature
    RANSAC fallback needs them); until then ``features`` is an empty (0, 33) array.
    """
    import open3d as o3d

    cfg = cfg or PreprocessConfig()
    seq = seq or SequenceConfig()
    v = check_voxel_size(voxel_size)
    keep = (
        outlier_mask(scan.points, v, cfg.outlier_min_cell_share)
        if cfg.outlier_min_cell_share > 0
        else np.ones(scan.num_points, bool)
    )
    raw = o3d.geometry.PointCloud(
        o3d.utility.Vector3dVector(np.ascontiguousarray(scan.points[keep], dtype=np.float64))
    )
    origin = np.zeros(3) if scan.sensor_origin is None else np.asarray(scan.sensor_origin, float)

    def level(voxel: float):
        down = raw.voxel_down_sample(voxel)
        down.estimate_normals(
            o3d.geometry.KDTreeSearchParamHybrid(
                radius=seq.normal_radius_voxels * voxel, max_nn=seq.normal_neighbours
            )
        )
        down.orient_normals_towards_camera_location(origin)
        return down, np.asarray(down.points).copy(), np.asarray(down.normals).copy()

    with single_threaded_blas():
        coarse, pts, nrm = level(v)
        if len(pts) < 10:
            raise ConfigError(
                f"{scan.name}: only {len(pts)} points at voxel size {v:.4g}; the voxel is too "
                "large for this scan"
            )
        fine_v = cfg.fine_voxel_ratio * v
        _, fine_pts, fine_nrm = level(fine_v)
        out = PreprocessedScan(
            name=scan.name,
            voxel_size=v,
            points=pts,
            normals=nrm,
            features=np.zeros((0, 33)),
            fine_voxel_size=fine_v,
            fine_points=fine_pts,
            fine_normals=fine_nrm,
            noise=plane_noise(fine_pts, fine_nrm),
            orientation="sensor origin",
            num_raw_points=scan.num_points,
            num_outliers_removed=int(np.count_nonzero(~keep)),
        )
    if seq.view_tests:
        set_viewpoint(out, origin, nrm)
        out.view_points = one_per_cell(scan.points, fine_v)
    out._cache["o3d_feature"] = coarse
    return out


def ensure_features(pre: PreprocessedScan, cfg: PreprocessConfig | None = None) -> None:
    """Compute the FPFH features of ``pre`` (N, 33) if they are not there yet (in place)."""
    import open3d as o3d

    if len(pre.features) == len(pre.points):
        return
    cfg = cfg or PreprocessConfig()
    with single_threaded_blas():
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(
            pre.o3d_cloud("feature"),
            o3d.geometry.KDTreeSearchParamHybrid(
                radius=cfg.fpfh_radius_voxels * pre.voxel_size, max_nn=cfg.fpfh_max_neighbours
            ),
        )
    pre.features = np.asarray(fpfh.data).T.copy()
    pre._cache["o3d_fpfh"] = fpfh
    pre._cache.pop("reduced_features", None)
