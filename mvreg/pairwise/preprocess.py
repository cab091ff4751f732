"""Stage 1: voxel sizes, downsampling, consistently oriented normals, FPFH features.

Takes loaded scans (:class:`~mvreg.io.loaders.Scan`, any units) and the ``preprocess``
section. Returns, per scan, a :class:`PreprocessedScan` in the scan's own frame and
units, kept at two resolutions:

* the *feature level*, voxel ``v`` (:func:`derive_voxel_size` from the data unless
  given): unit normals, FPFH (radius ``fpfh_radius_voxels * v``), feature RANSAC and
  coarse ICP;
* the *fine level*, voxel ``fine_voxel_ratio * v``: fine ICP, pair scores and the
  correspondences that become tracks.

The run's lengths come from :func:`derive_scales` (one check of the voxel,
:func:`check_voxel_size`) and :func:`with_noise` (after preprocessing), as a
:class:`~mvreg.scales.Scales`.

Guarantees:

* outliers: points alone in a feature-level voxel (:func:`outlier_mask`) are dropped;
  on the fine level a point also needs ``fine_min_neighbours`` other points within two
  fine voxels (not applied by :func:`resample`, which serves refinement);
* voxel from the data: per scan the voxel keeping about ``target_points_per_scan``
  points, the median over scans, at least ``min_voxel_spacings`` times the median point
  spacing; nothing assumes units (a scan in millimetres gets a voxel 1000 times that of
  the same scan in metres);
* normals: within a scan, signs agree -- by the view axis for a single view
  (:func:`single_view_axis`), else by a spanning tree over the neighbourhoods; one sign
  per scan then from the first cue the data gives: normals stored in the file, else a
  sensor origin stored in the file, else "outward" (sum of n . (p - centroid) > 0). No
  cue assumes the sensor at the origin;
* view direction: when at least ``min_view_facing`` of the normals face one direction
  (:func:`view_direction`) the scan is a single view seen from it and pairwise scoring
  checks free space (:mod:`mvreg.pairwise.scoring`); otherwise ``view_direction`` is
  None. A single view's sensor position (``viewpoint``) is the one stored in the file,
  else estimated from the raw points (:mod:`mvreg.pairwise.viewpoint`), else None
  (orthographic approximation along ``view_direction``);
* the same result whatever the executor, in the order of the scans.

Measurements behind these choices: ``docs/design/pairwise.md``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from mvreg.config.preprocess import PreprocessConfig
from mvreg.errors import ConfigError
from mvreg.executor import Executor, make_executor, map_shared, single_threaded_blas
from mvreg.pairwise.normals import estimate_normals
from mvreg.pairwise.view_projection import one_per_cell, set_viewpoint, surrounds, towards
from mvreg.scales import Scales

if TYPE_CHECKING:
    from mvreg.io.loaders import Scan


@dataclass
class PreprocessedScan:
    """A scan ready for pairwise alignment (local frame, the scan's units).

    Attributes:
        name: the scan's file name.
        voxel_size: feature-level voxel size ``v``.
        points, normals: (N, 3) float64 feature-level points and unit outward normals.
        features: (N, 33) float64 FPFH descriptors of ``points``.
        fine_voxel_size: voxel of the fine level.
        fine_points, fine_normals: (F, 3) float64 fine-level points and normals (oriented
            like the feature level).
        noise: median distance from a fine point's nearest neighbour to the point's tangent
            plane: the residual a perfect alignment leaves (data units); at least
            ``noise_floor_fine_voxels`` fine voxels.
        orientation: which cue fixed the normals' sign ("file normals", "sensor origin",
            "outward").
        num_raw_points: points of the loaded scan.
        view_direction: (3,) unit direction towards the sensor (orthographic
            approximation), or None when the scan does not look like a single view.
        view_facing: share of normals facing ``view_direction`` (n . d > 0.05).
        viewpoint: (3,) sensor position in the scan's frame (stored in the file, or
            estimated: :mod:`mvreg.pairwise.viewpoint`) for a single view; None: the view
            tests use the orthographic approximation along ``view_direction``.
        num_outliers_removed: raw points dropped as isolated (:func:`outlier_mask`).
        view_points: with a sensor position, one raw point per fine cell, strays kept
            (view tests; the stray filter drops far and thin-part samples of sparse scans).
    """

    name: str
    voxel_size: float
    points: np.ndarray
    normals: np.ndarray
    features: np.ndarray
    fine_voxel_size: float
    fine_points: np.ndarray
    fine_normals: np.ndarray
    noise: float
    orientation: str
    num_raw_points: int
    view_direction: np.ndarray | None = None
    view_facing: float = 0.0
    viewpoint: np.ndarray | None = None
    num_outliers_removed: int = 0
    view_points: np.ndarray | None = None
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __repr__(self) -> str:
        return (
            f"PreprocessedScan({self.name!r}, points={len(self.points)}, "
            f"fine_points={len(self.fine_points)}, voxel_size={self.voxel_size:.4g}, "
            f"noise={self.noise:.3g}, orientation={self.orientation!r})"
        )

    def __getstate__(self) -> dict:
        """Pickled (sent to a Dask worker) without the caches, which hold Open3D objects;
        the worker rebuilds them on demand from the arrays."""
        state = self.__dict__.copy()
        state["_cache"] = {}
        return state

    # Open3D objects and KD-trees, built once on demand.
    def o3d_cloud(self, level: str = "feature"):
        key = f"o3d_{level}"
        if key not in self._cache:
            pts, nrm = (
                (self.points, self.normals)
                if level == "feature"
                else (self.fine_points, self.fine_normals)
            )
            self._cache[key] = _to_o3d(pts, nrm)
        return self._cache[key]

    def o3d_features(self):
        if "o3d_fpfh" not in self._cache:
            import open3d as o3d

            feat = o3d.pipelines.registration.Feature()
            feat.data = np.ascontiguousarray(self.features.T)
            self._cache["o3d_fpfh"] = feat
        return self._cache["o3d_fpfh"]

    def fine_tree(self) -> cKDTree:
        if "fine_tree" not in self._cache:
            self._cache["fine_tree"] = cKDTree(self.fine_points)
        return self._cache["fine_tree"]


def _to_o3d(points: np.ndarray, normals: np.ndarray | None = None):
    import open3d as o3d

    pcd = o3d.geometry.PointCloud()
    pcd.points = o3d.utility.Vector3dVector(np.ascontiguousarray(points, dtype=np.float64))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals, dtype=np.float64))
    return pcd


def _voxel_cells(points: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """Cell index of each point (N,) and the number of points of each cell (C,)."""
    keys = np.floor((points - points.min(axis=0)) / voxel).astype(np.int64)
    dims = keys.max(axis=0) + 1
    flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
    _, cell, count = np.unique(flat, return_inverse=True, return_counts=True)
    return cell.reshape(-1), count


def _voxel_count(points: np.ndarray, voxel: float) -> int:
    """Cells holding two or more points (isolated outliers do not count)."""
    return int(np.count_nonzero(_voxel_cells(points, voxel)[1] >= 2))


def outlier_mask(points: np.ndarray, voxel: float, min_cell_share: float = 0.05) -> np.ndarray:
    """(N,) bool, True for points kept: those in voxels holding at least
    ``min_cell_share`` times the median number of points per voxel (and at least 2).

    Surfaces fill their voxels with many points; stray points (outliers, spray) sit alone
    in otherwise empty ones. Nothing is removed when voxels hold fewer than 4 points on
    median (too sparse to tell).
    """
    cell, count = _voxel_cells(points, voxel)
    median = float(np.median(count[cell]))  # per point: the typical cell a point sits in
    if median < 4:
        return np.ones(len(points), bool)
    return count[cell] >= max(2.0, min_cell_share * median)


def median_spacing(points: np.ndarray, max_samples: int = 4000) -> float:
    """Median distance from a point to its nearest neighbour (on an even subsample)."""
    stride = max(1, len(points) // max_samples)
    d, _ = cKDTree(points).query(points[::stride], k=2)
    return float(np.median(d[:, 1]))


def derive_voxel_size(
    scans: list[Scan], cfg: PreprocessConfig | None = None, executor: Executor | int = 2
) -> float:
    """Feature-level voxel size from the data (see the module docstring). Data units.

    The scans are measured on ``executor`` (an int: that many threads); the result does
    not depend on it.
    """
    cfg = cfg or PreprocessConfig()
    if cfg.voxel_size is not None:
        return float(cfg.voxel_size)
    if not scans:
        raise ConfigError("cannot derive a voxel size from zero scans")
    measured = map_shared(
        make_executor(executor), measure_voxel, cfg.target_points_per_scan, scans,
        labels=[f"scan {scan.name}" for scan in scans],
    )  # fmt: skip
    sizes, spacings = zip(*measured, strict=True)
    voxel = max(float(np.median(sizes)), cfg.min_voxel_spacings * float(np.median(spacings)))
    if not np.isfinite(voxel) or voxel <= 0:
        raise ConfigError("could not derive a voxel size from the data (degenerate scans)")
    return voxel


def measure_voxel(target: int, scan: Scan) -> tuple[float, float]:
    """(voxel keeping about ``target`` points of ``scan``, its median point spacing)."""
    pts = scan.points
    spacing = median_spacing(pts)
    if not spacing > 0:  # duplicated points: fall back on the extent
        spacing = float(np.linalg.norm(np.ptp(pts, axis=0))) / np.sqrt(len(pts))
    voxel = spacing * np.sqrt(max(len(pts), 1) / target)
    for _ in range(2):
        count = _voxel_count(pts, voxel)
        if count == 0:  # every point alone in a cell: fewer points than the target
            return max(voxel, spacing), spacing
        voxel *= np.sqrt(count / target)
    return voxel, spacing


def scan_spacing(_shared, scan: Scan) -> float:
    """:func:`median_spacing` of a scan's points (a task of :func:`map_shared`)."""
    return median_spacing(scan.points)


def _orient_like(normals: np.ndarray, points: np.ndarray, ref_points, ref_normals) -> np.ndarray:
    """Flip each normal to agree with the normal of the nearest reference point."""
    _, idx = cKDTree(ref_points).query(points)
    sign = np.where(np.einsum("ij,ij->i", normals, ref_normals[idx]) < 0, -1.0, 1.0)
    return normals * sign[:, None]


def check_voxel_size(voxel_size: float) -> float:
    """``voxel_size`` as a float; ConfigError unless it is finite and > 0. The one check
    of a voxel size, given or derived."""
    v = float(voxel_size)
    if not (np.isfinite(v) and v > 0):
        raise ConfigError(f"voxel_size must be > 0, got {voxel_size}")
    return v


# A given voxel below this share of the scans' median point spacing downsamples nothing and
# leaves each FPFH neighbourhood a handful of points: refused rather than run for nothing.
MIN_VOXEL_SPACINGS = 0.1
MAX_VOXEL_DIAGONAL = 0.2  # a given voxel above this share of the median diagonal: refused


def check_given_voxel(voxel: float, scans: Sequence[Scan], executor: Executor | int = 2):
    """ConfigError naming the value when a given voxel is absurd for the data: far below
    the scans' median point spacing (every point its own voxel), or above
    ``MAX_VOXEL_DIAGONAL`` times their median diagonal (a handful of points per scan)."""
    diagonal = float(np.median([np.linalg.norm(np.ptp(s.points, axis=0)) for s in scans]))
    if voxel > MAX_VOXEL_DIAGONAL * diagonal:
        raise ConfigError(
            f"voxel_size {voxel:.3g} is too large for scans of median diagonal {diagonal:.3g} "
            f"(data units): use at most {MAX_VOXEL_DIAGONAL * diagonal:.3g}, or leave it out "
            "to derive it from the data"
        )
    labels = [f"scan {s.name}" for s in scans]
    spacing = float(
        np.median(map_shared(make_executor(executor), scan_spacing, None, scans, labels=labels))
    )
    if spacing > 0 and voxel < MIN_VOXEL_SPACINGS * spacing:
        raise ConfigError(
            f"voxel_size {voxel:.3g} is far below the scans' median point spacing "
            f"{spacing:.3g} (data units): use at least {MIN_VOXEL_SPACINGS * spacing:.3g}, "
            "or leave it out to derive it from the data"
        )


def derive_scales(
    scans: Sequence[Scan], cfg: PreprocessConfig | None = None, executor: Executor | int = 2
) -> Scales:
    """The run's :class:`~mvreg.scales.Scales` before preprocessing: the feature voxel
    (``cfg.voxel_size`` when given, else :func:`derive_voxel_size`), the fine voxel
    (``fine_voxel_ratio`` times it) and where the voxel came from; ``noise`` 0 until
    :func:`with_noise`. ConfigError for a voxel that is not finite and > 0."""
    cfg = cfg or PreprocessConfig()
    voxel = check_voxel_size(derive_voxel_size(scans, cfg, executor))
    if cfg.voxel_size is not None and scans:
        check_given_voxel(voxel, scans, executor)
    return Scales(
        voxel=voxel,
        fine_voxel=cfg.fine_voxel_ratio * voxel,
        voxel_source="given" if cfg.voxel_size is not None else "derived",
    )


def with_noise(scales: Scales, pre: Sequence[PreprocessedScan]) -> Scales:
    """``scales`` with ``noise`` = the median of the preprocessed scans' own noise
    estimates (0 without scans). Per-scan noise stays on each scan."""
    return replace(scales, noise=float(np.median([p.noise for p in pre])) if pre else 0.0)


def scan_scales(pre: PreprocessedScan) -> Scales:
    """The voxel sizes ``pre`` was preprocessed at, for callers that pass no run-wide
    :class:`~mvreg.scales.Scales` (every scan of a run has the same ones)."""
    return Scales(voxel=pre.voxel_size, fine_voxel=pre.fine_voxel_size)


def preprocess(
    scan: Scan, voxel_size: float, cfg: PreprocessConfig | None = None
) -> PreprocessedScan:
    """Downsample, orient normals and compute FPFH for one scan (see the module docstring).

    Args:
        scan: a loaded scan.
        voxel_size: feature-level voxel, e.g. from :func:`derive_voxel_size` (the same for
            every scan of a run, so that features are comparable).
    """
    cfg = cfg or PreprocessConfig()
    voxel_size = check_voxel_size(voxel_size)
    with single_threaded_blas():
        return _preprocess(scan, voxel_size, cfg)


def preprocess_all(
    scans: Sequence[Scan],
    voxel_size: float,
    cfg: PreprocessConfig | None = None,
    executor: Executor | int = 2,
    progress: Callable[[PreprocessedScan], None] | None = None,
) -> list[PreprocessedScan]:
    """:func:`preprocess` of every scan on ``executor`` (an int: that many threads); the
    same result as one by one, in the order of ``scans``. ``progress`` is called (from
    the calling thread) as each scan is done, in that order."""
    cfg = cfg or PreprocessConfig()
    voxel_size = check_voxel_size(voxel_size)
    labels = [f"preprocessing scan {s.name}" for s in scans]
    ex = make_executor(executor)
    return map_shared(ex, preprocess_task, (voxel_size, cfg), scans, progress, labels)


def preprocess_task(shared: tuple[float, PreprocessConfig], scan: Scan) -> PreprocessedScan:
    """One scan's preprocessing as a task: ``shared`` is (voxel, section)."""
    voxel_size, cfg = shared
    with single_threaded_blas():
        return _preprocess(scan, voxel_size, cfg)


def _preprocess(scan: Scan, v: float, cfg: PreprocessConfig) -> PreprocessedScan:
    import open3d as o3d

    keep = outlier_mask(scan.points, v, cfg.outlier_min_cell_share)
    if cfg.outlier_min_cell_share > 0 and not keep.all():
        raw = _to_o3d(scan.points[keep], None if scan.normals is None else scan.normals[keep])
    else:
        raw = _to_o3d(scan.points, scan.normals)
    coarse = raw.voxel_down_sample(v)
    pts = np.asarray(coarse.points)
    if len(pts) < 10:
        raise ConfigError(
            f"{scan.name}: only {len(pts)} points at voxel size {v:.4g}; the voxel is too "
            "large for this scan"
        )
    file_normals = np.asarray(coarse.normals).copy() if scan.normals is not None else None
    coarse.normals = o3d.utility.Vector3dVector()
    estimate_normals(coarse, cfg.normal_radius_voxels * v, cfg.normal_max_neighbours)
    normals, orientation, seen_from = _oriented_normals(
        coarse, pts, file_normals, scan, keep, v, cfg
    )
    grow = seen_from is not None and surrounds(pts, seen_from)  # rings of a spinning sensor
    if grow:  # again, from neighbourhoods that span the surface; signs towards the sensor
        estimate_normals(coarse, cfg.normal_radius_voxels * v, cfg.normal_max_neighbours, grow)
        n = np.asarray(coarse.normals)
        normals = towards(n, pts, seen_from)
    coarse.normals = o3d.utility.Vector3dVector(normals)
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        coarse,
        o3d.geometry.KDTreeSearchParamHybrid(
            radius=cfg.fpfh_radius_voxels * v, max_nn=cfg.fpfh_max_neighbours
        ),
    )
    fine_v = cfg.fine_voxel_ratio * v
    fine_pts, fine_nrm = _resample(raw, fine_v, cfg, pts, normals, grow=grow)
    if seen_from is not None:
        fine_nrm = towards(fine_nrm, fine_pts, seen_from)
    out = PreprocessedScan(
        name=scan.name,
        voxel_size=v,
        points=pts.copy(),
        normals=normals,
        features=np.asarray(fpfh.data).T.copy(),
        fine_voxel_size=fine_v,
        fine_points=fine_pts,
        fine_normals=fine_nrm,
        noise=max(plane_noise(fine_pts, fine_nrm), cfg.noise_floor_fine_voxels * fine_v),
        orientation=orientation,
        num_raw_points=scan.num_points,
        num_outliers_removed=int(np.count_nonzero(~keep)) if cfg.outlier_min_cell_share else 0,
    )
    if seen_from is not None:  # a single view seen from there
        set_viewpoint(out, seen_from, normals)
        out.view_points = one_per_cell(scan.points, fine_v)
    else:
        direction, facing = view_direction(normals)
        out.view_facing = facing
        out.view_direction = direction if facing >= cfg.min_view_facing else None
        if out.view_direction is not None and scan.sensor_origin is not None:
            out.viewpoint = np.asarray(scan.sensor_origin, dtype=np.float64).copy()
    out._cache["o3d_feature"] = coarse
    out._cache["o3d_fpfh"] = fpfh
    return out


def _oriented_normals(coarse, pts, file_normals, scan: Scan, keep, v: float, cfg):
    """(normals, orientation cue, estimated sensor position or None) of the feature level:
    signs towards the sensor when its position is estimated, else by the view axis of a
    single view, else by a spanning tree; then one sign per scan from the first cue the
    data give (module docstring)."""
    axis = single_view_axis(pts, np.asarray(coarse.normals), v, cfg.max_view_occlusion)
    seen_from = _estimated_viewpoint(scan, keep, cfg, axis)
    if axis is None and seen_from is None:  # not one view: signs from a spanning tree
        k = min(cfg.orient_neighbours, len(pts) - 1)
        try:
            coarse.orient_normals_consistent_tangent_plane(k)
        except RuntimeError:
            pass  # degenerate neighbourhood graph: keep PCA signs, the global sign applies
    normals = np.asarray(coarse.normals).copy()
    if seen_from is not None:  # one sign per normal: towards the sensor
        normals = towards(normals, pts, seen_from)
    elif axis is not None:  # one sign per normal from the view axis (needs no spanning tree)
        normals *= np.where(normals @ axis < 0, -1.0, 1.0)[:, None]
    if file_normals is not None:
        vote, orientation = np.sum(np.einsum("ij,ij->i", normals, file_normals)), "file normals"
    elif seen_from is not None:
        vote, orientation = 1.0, "estimated sensor position"
    elif scan.sensor_origin is not None:
        vote = np.sum(np.sign(np.einsum("ij,ij->i", normals, scan.sensor_origin - pts)))
        orientation = "sensor origin"
    else:
        vote, orientation = np.sum(np.einsum("ij,ij->i", normals, pts - pts.mean(0))), "outward"
    if vote < 0:
        normals = -normals
    return normals, orientation, seen_from


def _estimated_viewpoint(scan: Scan, keep, cfg: PreprocessConfig, axis=None) -> np.ndarray | None:
    """The sensor position estimated from the raw points
    (:func:`~mvreg.pairwise.viewpoint.estimate_viewpoint`), when enabled and the file
    stores none; None when the points show no sensor's direction grid."""
    if scan.sensor_origin is not None or not cfg.estimate_viewpoint:
        return None
    from mvreg.pairwise.viewpoint import estimate_viewpoint

    c, _ = estimate_viewpoint(scan.points[keep], cfg.max_viewpoint_spread_ratio, axis)
    return c


def _resample(raw, voxel: float, cfg: PreprocessConfig, ref_pts, ref_nrm, strays=True, grow=False):
    down = raw.voxel_down_sample(voxel)
    if strays and cfg.fine_min_neighbours > 0:
        pts = np.asarray(down.points)
        near = cKDTree(pts).query_ball_point(pts, 2.0 * voxel, return_length=True) - 1
        keep = np.flatnonzero(near >= cfg.fine_min_neighbours)
        if 10 <= len(keep) < len(pts):
            down = down.select_by_index(keep)
    down.normals = type(down.normals)()
    estimate_normals(down, cfg.normal_radius_voxels * voxel, cfg.normal_max_neighbours, grow)
    pts = np.asarray(down.points).copy()
    return pts, _orient_like(np.asarray(down.normals).copy(), pts, ref_pts, ref_nrm)


def resample(
    scan: Scan, pre: PreprocessedScan, voxel_size: float, cfg: PreprocessConfig | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The scan at another voxel size, normals oriented like ``pre``'s.

    For refinement at a finer level than ``pre.fine_points``. Returns (P, 3) points and
    (P, 3) unit normals, float64, in the scan's local frame.
    """
    cfg = cfg or PreprocessConfig()
    grow = pre.viewpoint is not None and surrounds(pre.points, pre.viewpoint)
    return _resample(
        _to_o3d(scan.points), float(voxel_size), cfg, pre.points, pre.normals, False, grow
    )


def _fibonacci_cap(n: int, max_polar_deg: float = 180.0) -> np.ndarray:
    """n evenly spread unit vectors within ``max_polar_deg`` of +z (the sphere if 180)."""
    k = np.arange(n) + 0.5
    lowest = np.cos(np.radians(max_polar_deg))
    polar = np.arccos(1.0 - (1.0 - lowest) * k / n)
    azimuth = np.pi * (1.0 + 5.0**0.5) * k
    return np.stack(
        [np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], 1
    )


_DIRECTIONS = _fibonacci_cap(400)
_CAP = np.vstack([[0.0, 0.0, 1.0], _fibonacci_cap(400, 12.0)])


def view_direction(normals: np.ndarray, min_cos: float = 0.05) -> tuple[np.ndarray, float]:
    """Estimated direction towards the sensor, and the share of normals facing it.

    A range scan holds only surfaces facing its sensor, so its normals fill a cone around
    the view direction. Among the directions faced by (nearly) the largest share of
    normals -- a plateau, since many directions are faced by all of them -- the estimate
    is the centre of the cone: the one whose small cosines with the normals are largest
    (a low quantile, past the share that faces no direction: mis-oriented normals). The
    mean normal would be biased towards large faces. Searched over 400 directions on the
    sphere, then 400 within 12 degrees of the best, using about 500 of the normals.
    Returns ((3,) unit vector, share of all normals with cosine > ``min_cos``).
    """
    sample = normals[:: max(1, len(normals) // 500)]
    n = len(sample)
    candidates = _DIRECTIONS
    for _ in range(2):
        cos = candidates @ sample.T  # (directions, normals)
        share = np.mean(cos > min_cos, axis=1)
        top = share.max()
        k = min(n - 1, int((1.0 - top + 0.02) * n))
        margin = np.partition(cos, k, axis=1)[:, k]
        margin[share < top - 0.01] = -np.inf
        best = candidates[int(np.argmax(margin))]
        candidates = _CAP @ _rotation_from_z(best).T  # directions around the best
    return best, float(np.mean(normals @ best > min_cos))


def single_view_axis(
    points: np.ndarray, normals: np.ndarray, voxel: float, max_occlusion: float = 0.2
) -> np.ndarray | None:
    """Viewing axis of a single-view scan from its *unoriented* normals; None if not one view.

    Orientation by a spanning tree breaks on thin parts (ears, a handle, a spout): whole
    patches come out flipped, and a view direction estimated from them is far off. A
    range scan's unoriented normals are rarely perpendicular to the axis towards its
    sensor (grazing surfaces are sampled sparsely), so the axis is the direction whose
    small |cosines| with the normals (5% quantile) are largest: searched like
    :func:`view_direction`. The scan counts as one view when, seen along that axis
    (orthographic grid of 1.5 voxels), at most ``max_occlusion`` of its points lie more
    than two voxels (plus the depth a cell spans at the point's slope) behind the front-most
    point of their cell: a height field, as a single view is; merged or all-round scans
    are not. The sign of the axis is arbitrary.
    """
    axis, share = view_axis_occlusion(points, normals, voxel)
    return axis if share <= max_occlusion else None


def view_axis_occlusion(
    points: np.ndarray, normals: np.ndarray, voxel: float
) -> tuple[np.ndarray, float]:
    """(axis, occluded share) behind :func:`single_view_axis`."""
    sample = normals[:: max(1, len(normals) // 500)]
    k = int(0.05 * (len(sample) - 1))
    candidates = _DIRECTIONS[_DIRECTIONS[:, 2] >= 0]
    for _ in range(2):
        low = np.partition(np.abs(candidates @ sample.T), k, axis=1)[:, k]
        best = candidates[int(np.argmax(low))]
        candidates = _CAP @ _rotation_from_z(best).T
    a = np.cross(best, [1.0, 0.0, 0.0] if abs(best[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(best, a)
    cell = 1.5 * voxel
    u = np.floor(points @ a / cell).astype(np.int64)
    w = np.floor(points @ b / cell).astype(np.int64)
    _, cell_of = np.unique((u << 32) + w, return_inverse=True)
    depth = points @ best
    cos = np.abs(normals @ best)
    slack = 2.0 * voxel + cell * np.sqrt(np.clip(1 - cos**2, 0, 1)) / np.maximum(cos, 0.05)
    share = 1.0
    for sign in (1.0, -1.0):  # either end of the axis may face the sensor
        front = np.full(cell_of.max() + 1, -np.inf)
        np.maximum.at(front, cell_of, sign * depth)
        share = min(share, float(np.mean(sign * depth < front[cell_of] - slack)))
    return best, share


def _rotation_from_z(d: np.ndarray) -> np.ndarray:
    """A rotation taking +z to the unit vector d."""
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, d)
    c = float(z @ d)
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def plane_noise(points: np.ndarray, normals: np.ndarray) -> float:
    """Median |n_p . (q - p)| over points p with nearest other point q (same scan)."""
    _, idx = cKDTree(points).query(points, k=2)
    q = points[idx[:, 1]]
    r = np.abs(np.einsum("ij,ij->i", normals, q - points))
    return float(max(np.median(r), 1e-12 * (np.ptp(points) + 1.0)))
