"""Settings of the preprocess stage (voxel levels, normals, FPFH): mvreg.pairwise.preprocess."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class PreprocessConfig(BaseModel):
    """Stage 1 settings. Distances are in multiples of the voxel size ``v`` (given as
    ``voxel_size`` or derived from the data: mvreg.pairwise.preprocess.derive_scales)."""

    model_config = ConfigDict(extra="forbid")

    voxel_size: float | None = Field(
        None, gt=0, description="feature-level voxel size in data units; None = from the data"
    )
    target_points_per_scan: int = Field(
        2000, ge=100, description="derived voxel keeps about this many points per scan"
    )
    min_voxel_spacings: float = Field(
        3.0, gt=0, description="derived voxel >= this times the median point spacing"
    )
    fine_voxel_ratio: float = Field(0.5, gt=0, le=1, description="fine voxel / voxel")
    noise_floor_fine_voxels: float = Field(
        0.02,
        ge=0,
        description="the noise estimate is at least this many fine voxels: on noise-free "
        "scans (synthetic, CAD-sampled) it goes to zero, while two samplings of a curved "
        "surface still leave residuals, and every correct pair failed the residual test",
    )
    normal_radius_voxels: float = Field(2.0, gt=0, description="normal PCA radius / voxel")
    normal_max_neighbours: int = Field(30, ge=3, le=3000)
    orient_neighbours: int = Field(
        12, ge=3, le=1000, description="k of the orientation spanning tree"
    )
    fpfh_radius_voxels: float = Field(5.0, gt=0, description="FPFH radius / voxel")
    fpfh_max_neighbours: int = Field(100, ge=5, le=10_000)
    outlier_min_cell_share: float = Field(
        0.05, ge=0, lt=1, description="drop points in voxels this sparse (0 = keep all)"
    )
    fine_min_neighbours: int = Field(
        3,
        ge=0,
        description="fine level: drop points with fewer other points within 2 of its voxels "
        "(0 = keep all)",
    )
    min_view_facing: float = Field(
        0.8, ge=0, le=1, description="share of normals facing one direction for a 'view'"
    )
    max_view_occlusion: float = Field(
        0.2,
        ge=0,
        le=1,
        description="a scan is a single view when at most this share of its points lies "
        "behind another along its view axis",
    )
    estimate_viewpoint: bool = Field(
        True,
        description="single views: estimate the sensor position from the raw points' "
        "direction grid (mvreg.pairwise.viewpoint) for perspective view tests",
    )
    max_viewpoint_spread_ratio: float = Field(
        0.3,
        gt=0,
        le=1,
        description="keep the estimated sensor position only when the directions to the "
        "points from it are at least this much more regular than seen along its axis",
    )
