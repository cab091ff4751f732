"""Settings of pairwise alignment (mvreg.pairwise.aligners) and of the rotation search for
scans feature matching leaves unconnected (mvreg.pairwise.search)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class AlignConfig(BaseModel):
    """Stage 3 settings: feature matching, RANSAC, ICP, the scores and the acceptance rule
    that every pairwise aligner shares (mvreg.pairwise.aligners, mvreg.pairwise.decision).
    Distances are multiples of the feature voxel size ``v``."""

    model_config = ConfigDict(extra="forbid")

    feature_dims: int = Field(16, ge=1, le=33, description="PCA dims for FPFH matching")
    feature_match_eps: float = Field(
        1.0, ge=0, description="approximate descriptor search (0 = exact)"
    )
    ransac_backend: Literal["numpy", "open3d"] = "numpy"
    ransac_max_iterations: int = Field(4000, ge=1, le=400_000)
    ransac_confidence: float = Field(0.999, gt=0, lt=1)
    ransac_distance_voxels: float = Field(1.5, gt=0, description="RANSAC inlier distance / v")
    ransac_edge_length_ratio: float = Field(0.9, gt=0, lt=1)
    ransac_normal_angle_deg: float = Field(30.0, gt=0, le=180)
    ransac_validate_top: int = Field(
        8, ge=1, le=1000, description="hypotheses re-ranked on the scans"
    )
    ransac_guided: bool = Field(
        False,
        description="pairwise RANSAC: when plain draws stop short of the confidence, as many "
        "again drawn among pairwise-consistent matches (numpy backend; placing leftover "
        "scans on the model always does)",
    )
    ransac_hypotheses_tried: int = Field(
        8, ge=1, le=1000, description="distinct RANSAC hypotheses verified (ICP + acceptance rule)"
    )
    screen_icp_iterations: int = Field(
        3,
        ge=0,
        le=1000,
        description="feature-level ICP iterations before an alternative is screened",
    )
    icp_coarse_distance_voxels: float = Field(2.0, gt=0, description="feature-level ICP / v")
    icp_fine_distance_voxels: tuple[float, ...] = Field(
        (1.0, 0.5), description="fine-level ICP distances / v, one ICP run each"
    )
    icp_max_iterations: int = Field(30, ge=1, le=3000)
    icp_max_source_points: int = Field(1500, ge=100, le=10_000_000)
    icp_min_normal_cos: float = Field(0.5, ge=-1, le=1)
    score_distance_voxels: float = Field(1.0, gt=0, description="neighbour distance / v")
    score_min_normal_cos: float = Field(0.7, ge=-1, le=1)
    tight_residual_ratio: float = Field(3.0, gt=0, description="overlap residual / noise")
    min_overlap_ratio: float = Field(0.1, ge=0, le=1)
    max_residual_ratio: float = Field(3.5, gt=0)
    min_correspondences: int = Field(50, ge=3)
    max_free_space_violation: float = Field(
        0.005, ge=0, le=1, description="share of points seen in front of the other view"
    )
    max_free_space_apart: float = Field(
        0.5,
        gt=0,
        le=1,
        description="verification: a share of a scan's facing points in any other registered "
        "scan's free space above this contradicts one of the two poses, surface shared or not "
        "(right poses read a few percent: docs/design/verification.md)",
    )
    free_space_tolerance_voxels: float = Field(1.0, gt=0, description="depth slack / v")
    max_unseen_violation: float = Field(
        0.008,
        ge=0,
        le=1,
        description="share of points facing the other view's sensor where it saw nothing",
    )
    unseen_radius_voxels: float = Field(
        3.0, gt=0, description="no point of the other view within this lateral distance / v"
    )
    free_space_min_facing_cos: float = Field(0.7, ge=0, lt=1)
    relative_residual_factor: float | None = Field(
        1.5,
        gt=1,
        description="align_pairs: reject residual_ratio above this times the reference of "
        "the best-overlapping pairs (None: off)",
    )
    relative_residual_floor_fine_voxels: float = Field(
        0.05,
        ge=0,
        description="align_pairs: a median residual below this many fine voxels passes the "
        "relative test whatever the reference (noise-free scans: residuals of correct pairs "
        "differ by the sampling alone, tiny but several times apart)",
    )
    coarse_gate_slack: float = Field(
        3.0, ge=1, description="feature-level ICP must pass the rule loosened this much"
    )


class SearchConfig(BaseModel):
    """Stage 3b settings: which scans and partners are tried (mvreg.pairwise.search) and
    the screening of the rotation-search aligner. Distances in multiples of the voxel
    size ``v``."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = True
    weak_scans: bool = Field(
        False,
        description="after a first pass that leaves scans unverified, search their "
        "rejected pairs again and run a second pass, kept when it verifies more scans "
        "(off by default: docs/design/verification.md)",
    )
    joint: bool = Field(
        True,
        description="after a first pass that leaves scans unverified, gather several "
        "hypotheses for their pairs (the rotation search's among them), choose one per "
        "pair jointly by agreement around cycles, and run a second pass, kept when it "
        "verifies more scans (mvreg.pairwise.joint)",
    )
    joint_partners: int = Field(
        4, ge=1, le=1000, description="pairs searched per unverified scan (nearest by descriptor)"
    )
    joint_max_scans: int = Field(
        64,
        ge=0,
        le=1000000,
        description="runs with more scans skip the joint choice (its second pass is a whole "
        "second global stage: 200 scans of 400 points took 4 min more)",
    )
    joint_max_pairs: int = Field(
        48, ge=1, le=100000,
        description="pairs searched in all by the joint choice (each scan's nearest first, "
        "in turn), so a run with hundreds of unverified scans stays bounded",
    )  # fmt: skip
    partners: int = Field(3, ge=1, le=1000, description="scans of the connected set tried per scan")
    offset_deg: float = Field(20.0, ge=0, le=90, description="turn of the group's copies")
    screen_source_points: int = Field(500, ge=50)
    screen_distances_voxels: tuple[float, ...] = Field((8.0, 4.0, 2.0))
    screen_iterations: int = Field(6, ge=1, le=1000, description="ICP iterations per distance")
