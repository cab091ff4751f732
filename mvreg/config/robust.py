"""Settings of the robust re-weighting of pairs after the global solve."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class RobustConfig(BaseModel):
    """Iteratively re-weighted pairs after the global solve (stage 6).

    A pair's residual is the median distance between its corresponding points under the
    global poses; its weight is w = 1 / (1 + (r / c)^2)^2 (Geman-McClure-like), with
    c = ``scale_factor`` times the median pair residual (but at least ``min_scale_voxels``
    feature voxels); weights below ``zero_weight`` become 0 (the pair is listed as bad).
    After refinement each accepted pair is compared with the final poses
    (``final_disagreement_voxels``). Why: docs/design/globalstage.md.
    """

    model_config = ConfigDict(extra="forbid")

    rounds: int = Field(10, ge=0, le=1000, description="at most; stops when the weights settle")
    scale_factor: float = Field(3.0, gt=0)
    min_scale_voxels: float = Field(0.25, gt=0)
    zero_weight: float = Field(0.05, ge=0, lt=1)
    cycle_check_voxels: float | None = Field(
        2.0,
        gt=0,
        description="before the solve, accepted pairs contradicted by more cycles of 3-4 "
        "pairs than confirm them (discrepancy above this many feature voxels) start at "
        "weight 0 (mvreg.pairwise.consistency); None: off",
    )
    final_disagreement_voxels: float | None = Field(
        1.0,
        gt=0,
        description="after refinement, an accepted pair whose own pose moves the overlap "
        "of its scans (median) more than this many feature voxels away from the final poses "
        "is listed as bad (final weight 0); None: off",
    )
