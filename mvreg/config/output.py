"""Settings of the outputs (merged cloud, rerun recording)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class OutputConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    merged_voxel_size: float | None = Field(
        None, gt=0, description="voxel of merged.ply (default: the fine voxel)"
    )
    merged_format: Literal["ply", "laz", "e57"] = Field(
        "ply",
        description="also write every point of every registered scan, one scan per input "
        "with its pose, as merged.laz or merged.e57 (merged.ply is always written)",
    )
    rrd: bool = True
    max_points_per_scan_in_recording: int = Field(50_000, ge=100)
    record_pair_correspondences: bool = Field(
        True, description="log each pair's correspondences (capped) into the recording"
    )
