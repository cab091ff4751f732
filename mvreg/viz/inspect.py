"""Read a written ``.rrd`` back with rerun's own reader (for tests and checks).

Uses ``rerun.chunk.RrdReader`` (rerun-sdk 0.41): every chunk of the first recording
store is loaded, grouped by entity path; the blueprint store is read for its views.
"""

from __future__ import annotations

import os
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mvreg.viz.recorder import SOLVER_TIMELINE


class RecordingFile:
    """Contents of an ``.rrd`` file, by entity.

    Entities are named as rerun prints them (``/raw/scan\\ 0.ply``); every method also
    accepts a list of unescaped parts (``["raw", "scan 0.ply"]``).

    Attributes:
        application_id, recording_id: of the (first) recording store.
        entities: set of entity paths holding data (rerun's own ``/__...`` excluded).
        blueprint_views: one dict per view of the blueprint (``class_identifier``,
            ``name``, ``origin``); empty when the file holds no blueprint.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        from rerun.chunk import RrdReader

        self.path = Path(path)
        reader = RrdReader(self.path)
        recordings = reader.recordings()
        if not recordings:
            raise ValueError(f"{self.path}: no recording in the file")
        self.application_id = recordings[0].application_id
        self.recording_id = recordings[0].recording_id
        self._chunks = defaultdict(list)
        for chunk in reader.stream(store=recordings[0]):
            self._chunks[chunk.entity_path].append(chunk)
        self.entities = {e for e in self._chunks if not e.startswith("/__")}
        self.blueprint_views = []
        for store in reader.blueprints():
            for chunk in reader.stream(store=store):
                batch = chunk.to_record_batch()
                if "ViewBlueprint:class_identifier" in batch.schema.names:
                    self.blueprint_views.append(
                        {
                            "class_identifier": _first(batch, "ViewBlueprint:class_identifier"),
                            "name": _first(batch, "ViewBlueprint:display_name"),
                            "origin": _first(batch, "ViewBlueprint:space_origin"),
                        }
                    )

    def has(self, entity: str | Sequence[str]) -> bool:
        return _entity_path(entity) in self._chunks

    def is_static(self, entity: str | Sequence[str]) -> bool:
        return all(chunk.is_static for chunk in self._chunks_of(entity))

    def components(self, entity: str | Sequence[str]) -> set[str]:
        """Column names of an entity, e.g. ``{"Points3D:positions", "Points3D:colors"}``."""
        names: set[str] = set()
        for chunk in self._chunks_of(entity):
            names.update(chunk.to_record_batch().schema.names)
        return {n for n in names if not n.startswith("rerun.controls")}

    def column(self, entity: str | Sequence[str], component: str) -> list:
        """All rows of one component, over every chunk (each row is a list of values)."""
        rows: list = []
        for chunk in self._chunks_of(entity):
            batch = chunk.to_record_batch()
            if component in batch.schema.names:
                rows.extend(batch.column(component).to_pylist())
        return rows

    def latest(self, entity: str | Sequence[str], component: str) -> np.ndarray:
        """The last logged row of a component as an array (e.g. ``(N, 3)`` positions)."""
        rows = self.column(entity, component)
        if not rows:
            raise KeyError(f"{_entity_path(entity)} has no {component}")
        return np.asarray(rows[-1])

    def scalars(
        self, entity: str | Sequence[str], timeline: str = SOLVER_TIMELINE
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(steps (K,) int64, values (K,) float64)`` of a ``Scalars`` entity, by step."""
        steps: list[int] = []
        values: list[float] = []
        for chunk in self._chunks_of(entity):
            batch = chunk.to_record_batch()
            if timeline not in batch.schema.names:
                continue
            steps.extend(batch.column(timeline).to_pylist())
            values.extend(row[0] for row in batch.column("Scalars:scalars").to_pylist())
        order = np.argsort(steps, kind="stable")
        return np.asarray(steps, dtype=np.int64)[order], np.asarray(values)[order]

    def _chunks_of(self, entity: str | Sequence[str]) -> list:
        path = _entity_path(entity)
        if path not in self._chunks:
            raise KeyError(f"{self.path}: no entity {path}")
        return self._chunks[path]


def _entity_path(entity: str | Sequence[str]) -> str:
    if isinstance(entity, str):
        return entity if entity.startswith("/") else "/" + entity
    import rerun as rr

    return rr.new_entity_path(list(entity))


def _first(batch, column: str):
    rows = batch.column(column).to_pylist() if column in batch.schema.names else []
    if rows and isinstance(rows[0], list):
        return rows[0][0] if rows[0] else None
    return rows[0] if rows else None
