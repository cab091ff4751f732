"""Settings of the multiview refinement rounds and the joint point-to-plane ICP."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class RefineConfig(BaseModel):
    """Multiview ICP rounds (stage 7): correspondences between all overlapping scans
    recomputed with the current global poses, then a warm-started global re-solve.

    By default each pair is first refined by point-to-plane ICP and its correspondences
    are taken under that refined pose (``correspondences="pairwise-icp"``). After the
    rounds, a joint point-to-plane ICP moves all poses together (``joint_icp_*``,
    :mod:`mvreg.globalstage.joint_icp`). Why: docs/design/globalstage.md.
    """

    model_config = ConfigDict(extra="forbid")

    rounds: int = Field(3, ge=0, le=100, description="--refine N")
    distance_voxels: tuple[float, ...] = Field(
        (1.0, 0.6, 0.3), description="correspondence distance / feature voxel, per round"
    )
    min_correspondences: int = Field(30, ge=3)
    correspondences: Literal["pairwise-icp", "nearest"] = Field(
        "pairwise-icp",
        description="pairwise-icp: each overlapping pair is first refined by point-to-plane "
        "ICP from its relative pose under the global poses and matched (mutual nearest "
        "neighbours) under that pose; nearest: matched under the global poses",
    )
    icp_points: int = Field(
        3000, ge=10, description="pairwise-icp: source points of each pair's ICP (evenly strided)"
    )
    last_round_icp_points: int = Field(
        1000,
        ge=10,
        description="the same in the last round (the densest level, after the others have "
        "moved the poses along the planes): 80 builtin scans, refinement 35.3 -> 27.6 s at "
        "the same accuracy (docs/design/globalstage.md)",
    )
    last_round_correspondences: Literal["pairwise-icp", "nearest"] = Field(
        "pairwise-icp",
        description="the last round's matching; nearest (no pair ICP) is faster still but "
        "lets sparse scans of planar parts slide (featuretype sparse: 1.69 -> 2.51 deg)",
    )
    dense_voxel_ratio: float | None = Field(
        0.25,
        gt=0,
        description="the last round uses the raw scans resampled at this fraction of the "
        "feature voxel (denser correspondences, less sampling bias); None: fine points",
    )
    joint_icp_iterations: int = Field(
        30,
        ge=0,
        le=1000,
        description="after the rounds, at most this many Gauss-Newton iterations of joint "
        "point-to-plane ICP over all poses (mvreg.joint_icp; it stops earlier when no scan "
        "moves more than joint_icp_tolerance_voxels); 0: off",
    )
    joint_icp_distance_voxels: float = Field(
        0.5, gt=0, description="joint ICP correspondence distance / feature voxel"
    )
    joint_icp_points_per_pair: int = Field(
        4000, ge=100, description="joint ICP: source points per pair (evenly strided)"
    )
    joint_icp_tolerance_voxels: float = Field(
        0.01, gt=0, description="joint ICP stops when no scan moves more than this"
    )
    joint_icp_model_normals: bool = Field(
        True,
        description="joint ICP: normals re-estimated on the union of the registered scans "
        "at the start poses, and once more at the converged poses, from which it runs again "
        "(mvreg.globalstage.joint_icp.model_normals); False: the scans' own normals",
    )
    joint_icp_max_move_voxels: float = Field(
        1.0,
        gt=0,
        description="joint ICP results that move any point of a scan further than this "
        "(feature voxels) from the certified poses are not kept",
    )
