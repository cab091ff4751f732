"""Configuration of a run, as pure data: one pydantic model per stage, one root model.

Defaults < config file (JSON or YAML, ``--config``) < ``--set section.field=value`` and the
named command-line options. This package imports nothing of the algorithms: a stage
receives its own section (and plain values such as the scales of the data), never the
whole root. Values derived from the data (the voxel sizes) are resolved once by the
pipeline and written back into the saved configuration (``RegisterConfig.resolved``).
"""

from __future__ import annotations

import json
from pathlib import Path

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
)

from mvreg.config.align import AlignConfig, SearchConfig
from mvreg.config.output import OutputConfig
from mvreg.config.pairs import PairsConfig
from mvreg.config.preprocess import PreprocessConfig
from mvreg.config.refine import RefineConfig
from mvreg.config.robust import RobustConfig
from mvreg.config.sequence import SequenceConfig
from mvreg.config.solve import SolveConfig
from mvreg.config.tracks import TracksConfig
from mvreg.errors import ConfigError

__all__ = [
    "AlignConfig",
    "OutputConfig",
    "PairsConfig",
    "PreprocessConfig",
    "RefineConfig",
    "RegisterConfig",
    "RobustConfig",
    "SearchConfig",
    "SequenceConfig",
    "SolveConfig",
    "TracksConfig",
    "load_config",
]


class RegisterConfig(BaseModel):
    """Everything ``register`` does, by stage."""

    model_config = ConfigDict(extra="forbid")

    seed: int = Field(0, ge=0, description="same seed, same poses")
    threads: int = Field(
        2, ge=1, le=1024, description="in-process threads for per-scan and per-pair work"
    )
    workers: int | None = Field(
        None,
        ge=1,
        description="worker processes of a local Dask cluster for preprocessing and pairwise "
        "alignment (None: in-process threads)",
    )
    scheduler: str | None = Field(
        None,
        min_length=1,
        description="address of a running Dask scheduler (tcp://host:8786) for preprocessing "
        "and pairwise alignment, instead of workers",
    )
    min_points: int = Field(100, ge=3, description="a scan needs at least this many points")
    max_points_per_scan: int = Field(
        50_000_000,
        ge=3,
        description="a scan with more points is refused with a message (memory)",
    )
    preprocess: PreprocessConfig = Field(default_factory=PreprocessConfig)
    pairs: PairsConfig = Field(default_factory=PairsConfig)
    align: AlignConfig = Field(default_factory=AlignConfig)
    search: SearchConfig = Field(default_factory=SearchConfig)
    tracks: TracksConfig = Field(default_factory=TracksConfig)
    solve: SolveConfig = Field(default_factory=SolveConfig)
    robust: RobustConfig = Field(default_factory=RobustConfig)
    refine: RefineConfig = Field(default_factory=RefineConfig)
    output: OutputConfig = Field(default_factory=OutputConfig)
    sequence: SequenceConfig = Field(default_factory=SequenceConfig)

    @field_validator("scheduler")
    @classmethod
    def _one_cluster(cls, scheduler: str | None, info: ValidationInfo) -> str | None:
        if scheduler is not None and info.data.get("workers") is not None:
            raise ValueError("give either workers (a local Dask cluster) or scheduler, not both")
        return scheduler


def _parse_config(path: Path, text: str):
    """The JSON (or YAML, by suffix) text of a config file; ConfigError in one line."""
    if path.suffix.lower() not in (".yaml", ".yml"):
        try:
            return json.loads(text)
        except (ValueError, TypeError, RecursionError) as e:
            raise ConfigError(f"{path}: not valid JSON ({e})") from None
    try:
        import yaml
    except ImportError:
        raise ConfigError(f"{path}: YAML needs PyYAML; use JSON instead") from None
    try:
        return yaml.safe_load(text) or {}
    except (yaml.YAMLError, ValueError, TypeError, RecursionError) as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        what = getattr(e, "problem", None) or str(e).splitlines()[0]
        raise ConfigError(f"{path}: not valid YAML ({where}{what})") from None


def load_config(
    path: str | Path | None = None, base: RegisterConfig | None = None, **overrides
) -> RegisterConfig:
    """Defaults (or ``base``), then the file (JSON, or YAML when PyYAML is installed), then
    overrides.

    ``overrides`` use dotted keys for nested fields: ``{"solve.solver": "gpm",
    "preprocess.voxel_size": 0.002, "seed": 3}``; None values are ignored.
    """
    if base is not None and path is not None:
        raise ConfigError("give a base configuration or a config file, not both")
    data: dict = base.model_dump() if base is not None else {}
    if path is not None:
        path = Path(path)
        try:
            text = path.read_text()
        except OSError as e:
            raise ConfigError(f"{path}: cannot read config ({e.strerror})") from None
        data = _parse_config(path, text)
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
        raise ConfigError(
            f"{'config' if path is None else path}: {validation_message(e)}"
        ) from None


def validation_message(e: ValidationError) -> str:
    """One line for a pydantic error: the field, what it should be, the value given.

    The alternatives of a union (``'auto'`` or a positive number) are joined with "or"."""
    errors = e.errors()
    field = [str(x) for x in errors[0]["loc"] if isinstance(x, int) or str(x).isidentifier()]
    same = [
        err
        for err in errors
        if [str(x) for x in err["loc"] if isinstance(x, int) or str(x).isidentifier()] == field
    ]
    msgs = list(dict.fromkeys(err["msg"].removeprefix("Value error, ") for err in same))
    got = f" (got {errors[0]['input']!r})" if "input" in errors[0] else ""
    return f"{'.'.join(field) or 'config'}: {' or '.join(msgs)}{got}"
