"""The lengths of a run, derived from the data once and passed explicitly.

Every distance threshold in mvreg is a multiple of one of these, never a constant in data
units, so that scans in millimetres and in kilometres behave alike.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class Scales:
    """Lengths in data units.

    voxel: the feature voxel (FPFH, RANSAC, pair scores; ``preprocess.voxel_size``).
    fine_voxel: the fine voxel (ICP, tracks, refinement): ``voxel * fine_voxel_ratio``.
    noise: the median of the scans' noise estimates (std. of points about their local
        plane at the fine level), 0 until the scans are preprocessed.
    voxel_source: "given" (``--voxel-size``) or "derived" (from the point spacing).
    """

    voxel: float
    fine_voxel: float
    noise: float = 0.0
    voxel_source: str = "derived"

    def to_dict(self) -> dict:
        return asdict(self)
