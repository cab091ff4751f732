"""Settings of the candidate-pair stage: mvreg.pairwise.candidates."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class PairsConfig(BaseModel):
    """Stage 2 settings."""

    model_config = ConfigDict(extra="forbid")

    all_pairs_max_scans: int = Field(16, ge=2, description="try every pair up to this many")
    neighbours_per_scan: int = Field(8, ge=1, description="k most similar scans above it")
