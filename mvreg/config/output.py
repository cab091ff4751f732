"""Settings of the outputs (merged cloud, rerun recording)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class OutputConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    merged_voxel_size: float | None = Field(
        None, gt=0, description="voxel of merged.ply (default: the fine voxel)"
    )
    rrd: bool = True
    max_points_per_scan_in_recording: int = Field(50_000, ge=100)
    record_pair_correspondences: bool = Field(
        True, description="log each pair's correspondences (capped) into the recording"
    )
