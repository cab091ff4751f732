"""Settings of the sequence stages (odometry, gaps, sequential pairs, loop closures)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class SequenceConfig(BaseModel):
    """Settings of the sequence stages (odometry, gaps, sequential pairs, loop closures).

    Distances are relative to the data: KISS-ICP's voxel to the largest point range, the
    loop radius to the median point range.
    """

    model_config = ConfigDict(extra="forbid")

    dataloader: str | None = Field(
        None,
        description="read the source with this KISS-ICP dataloader (kitti, generic, rosbag, "
        "mcap, ouster, ...) instead of as a folder of scan files",
    )
    dataloader_sequence: str | None = Field(
        None, description="the dataloader's sequence argument (KITTI: 00, 01, ...)"
    )
    dataloader_max_frames: int | None = Field(None, ge=2, description="read at most this many")
    odometry_voxel_ranges: float = Field(
        0.01, gt=0, le=0.5, description="KISS-ICP voxel / largest point range"
    )
    odometry_threads: int = Field(1, ge=0, description="KISS-ICP threads (0: all cores)")
    gap_factor: float = Field(
        1.5, gt=1, description="a time step above this times the median step is a gap"
    )
    skip_pairs: int = Field(1, ge=0, description="also pair scan k with k+2 .. k+1+skip_pairs")
    fallback_ransac: bool = Field(True, description="feature RANSAC when ICP from odometry fails")
    loop_radius_ranges: float = Field(
        0.5, gt=0, description="loop-closure search radius / median point range"
    )
    loop_drift_fraction: float = Field(
        0.05, ge=0, description="the radius grows by this times the path between the scans"
    )
    loop_min_frames: int = Field(10, ge=2, description="loop pairs are at least this many apart")
    loop_min_path_radii: float = Field(
        2.0, ge=0, description="path between a loop pair's scans >= this times the radius"
    )
    loop_max_per_scan: int = Field(2, ge=0, description="nearest earlier candidates per scan")
    loop_min_overlap_ratio: float = Field(0.3, ge=0, le=1)
    normal_neighbours: int = Field(
        10, ge=3, description="normals of range scans: PCA of this many nearest points"
    )
    normal_radius_voxels: float = Field(
        6.0, gt=0, description="... within this many voxels of the level (feature or fine)"
    )
    view_tests: bool = Field(
        True,
        description="each frame is a view from its sensor (the frame origin): pairs and "
        "verification test free space (a frame put where another frame saw empty space)",
    )
    correspondences: Literal["pose", "nearest"] = Field(
        "pose", description="tracks from each pair's pose (pose_tracks) or nearest points"
    )
    correspondences_per_pair: int | None = Field(
        400, ge=4, description="tracks: thin each pair to this many (if tracks sets none)"
    )
    min_normal_cos: float = Field(
        0.7,
        ge=-1,
        le=1,
        description="tracks: normals must agree (unless tracks.min_normal_cos is given); "
        "LiDAR normals are noisier than a range scanner's, and the sequence benchmark "
        "was measured at 0.7",
    )
