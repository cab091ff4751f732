"""Settings of the tracks stage (correspondences -> tracks -> patch problem)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class TracksConfig(BaseModel):
    """Stage 4 settings (mvreg.pairwise.tracks). Distances are multiples of the feature
    voxel size ``v``.

    ``min_normal_cos`` also holds in the refinement's matching and pair ICP; at 0.9 (26
    degrees) points on either side of a sharp edge do not match each other
    (measurements: docs/design/pairwise.md).
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
