"""Typed, layered configuration of ``register``: one pydantic model per stage.

Defaults < config file (JSON or YAML, ``--config``) < explicit options. Derived values
(the voxel size from the data) are filled in by the pipeline and written, resolved, into
``report.json`` next to the results.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from mvreg.errors import ConfigError
from mvreg.pairwise.align import AlignConfig
from mvreg.pairwise.candidates import PairsConfig
from mvreg.pairwise.preprocess import PreprocessConfig
from mvreg.pairwise.search import SearchConfig
from mvreg.pairwise.tracks import TracksConfig


class SolveConfig(BaseModel):
    """The global stage (mvreg.solver.solve)."""

    model_config = ConfigDict(extra="forbid")

    solver: str = "reg-admm"
    method: Literal["auto", "dense", "matrix-free"] = "auto"
    rho: Literal["auto"] | float = "auto"
    max_iter: int = Field(500, ge=1)
    allow_reflections: bool = False


class RobustConfig(BaseModel):
    """Iteratively re-weighted pairs after the global solve (stage 6).

    A pair's residual is the median distance between its corresponding points under the
    global poses; its weight is w = 1 / (1 + (r / c)^2)^2 (Geman-McClure-like), with
    c = ``scale_factor`` times the median pair residual (but at least ``min_scale_voxels``
    feature voxels); weights below ``zero_weight`` become 0 (the pair is listed as bad).

    A wrong pair links the points that happen to lie close under its wrong pose, near the
    centre of its error, so its residual under the right poses stays modest and its weight
    can settle above ``zero_weight`` (an injected 12-degree error on the teapot: weight
    0.33). The final poses after refinement no longer use the pairs' own poses at all, so
    each accepted pair is then compared with them (``final_disagreement_voxels``).
    """

    model_config = ConfigDict(extra="forbid")

    rounds: int = Field(10, ge=0, description="at most; stops when the weights settle")
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


class RefineConfig(BaseModel):
    """Multiview ICP rounds (stage 7): correspondences between all overlapping scans
    recomputed with the current global poses, then a warm-started global re-solve.

    Nearest-neighbour pairs under the current poses pull only at the scale of the point
    spacing and barely at all along a plane (both scans' samples of a face look alike
    wherever they slide), so on CAD-like parts the rounds stalled near the start
    (``correspondences="nearest"``). By default each pair is first refined by
    point-to-plane ICP, which does move along planes as far as the other faces require,
    and its correspondences are taken under that refined pose.

    After the rounds, a joint point-to-plane ICP moves all poses together
    (``joint_icp_*``, :mod:`mvreg.joint_icp`): each pair then constrains only the
    directions its overlap does, which the rounds' point-to-point tracks cannot express.
    """

    model_config = ConfigDict(extra="forbid")

    rounds: int = Field(3, ge=0, description="--refine N")
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
    dense_voxel_ratio: float | None = Field(
        0.25,
        gt=0,
        description="the last round uses the raw scans resampled at this fraction of the "
        "feature voxel (denser correspondences, less sampling bias); None: fine points",
    )
    joint_icp_iterations: int = Field(
        10,
        ge=0,
        description="after the rounds, at most this many Gauss-Newton iterations of joint "
        "point-to-plane ICP over all poses (mvreg.joint_icp); 0: off",
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
    joint_icp_max_move_voxels: float = Field(
        1.0,
        gt=0,
        description="joint ICP results that move any point of a scan further than this "
        "(feature voxels) from the certified poses are not kept",
    )


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


class RegisterConfig(BaseModel):
    """Everything ``register`` does, by stage."""

    model_config = ConfigDict(extra="forbid")

    seed: int = 0
    min_points: int = Field(100, ge=3, description="a scan needs at least this many points")
    preprocess: PreprocessConfig = Field(default_factory=PreprocessConfig)
    pairs: PairsConfig = Field(default_factory=PairsConfig)
    align: AlignConfig = Field(default_factory=AlignConfig)
    search: SearchConfig = Field(default_factory=SearchConfig)
    tracks: TracksConfig = Field(default_factory=TracksConfig)
    solve: SolveConfig = Field(default_factory=SolveConfig)
    robust: RobustConfig = Field(default_factory=RobustConfig)
    refine: RefineConfig = Field(default_factory=RefineConfig)
    output: OutputConfig = Field(default_factory=OutputConfig)


def load_config(path: str | Path | None = None, **overrides) -> RegisterConfig:
    """Defaults, then the file (JSON, or YAML when PyYAML is installed), then overrides.

    ``overrides`` use dotted keys for nested fields: ``{"solve.solver": "gpm",
    "preprocess.voxel_size": 0.002, "seed": 3}``; None values are ignored.
    """
    data: dict = {}
    if path is not None:
        path = Path(path)
        try:
            text = path.read_text()
        except OSError as e:
            raise ConfigError(f"{path}: cannot read config ({e.strerror})") from None
        try:
            if path.suffix.lower() in (".yaml", ".yml"):
                try:
                    import yaml
                except ImportError:
                    raise ConfigError(f"{path}: YAML needs PyYAML; use JSON instead") from None
                data = yaml.safe_load(text) or {}
            else:
                data = json.loads(text)
        except (ValueError, TypeError) as e:
            raise ConfigError(f"{path}: not valid JSON/YAML ({e})") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{path}: the config must be a mapping of stage -> settings")
    for key, value in overrides.items():
        if value is None:
            continue
        node = data
        parts = key.split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
    try:
        return RegisterConfig.model_validate(data)
    except ValidationError as e:
        err = e.errors()[0]
        where = ".".join(str(x) for x in err["loc"])
        raise ConfigError(
            f"{'config' if path is None else path}: {where}: {err['msg']}"
            + (f" (got {err.get('input')!r})" if "input" in err else "")
        ) from None
