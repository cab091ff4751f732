"""Settings of the tracks stage (correspondences -> tracks -> patch problem)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class TracksConfig(BaseModel):
    """Stage 4 settings. Distances are multiples of the feature voxel size ``v``.

    ``min_normal_cos`` also holds in the refinement's matching and pair ICP. At 0.9 (26
    degrees) rather than 0.7, points on either side of a sharp edge no longer match each
    other: fandisk seed 0, clean, went from 0.186 to 0.117 degrees worst rotation error,
    and the real bunny from 0.446 to 0.429 mm worst translation error.
    """

    model_config = ConfigDict(extra="forbid")

    max_correspondence_voxels: float = Field(
        1.0, gt=0, description="mutual nearest neighbours within this distance / v"
    )
    min_normal_cos: float = Field(0.9, ge=-1, le=1, description="normals must agree")
    max_correspondences_per_pair: int | None = Field(
        None, ge=4, description="evenly thin a pair's correspondences to at most this many"
    )
    split_conflicting_tracks: bool = Field(
        True, description="split tracks that see a scan twice (else drop them)"
    )
