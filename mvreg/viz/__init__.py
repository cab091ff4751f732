"""Visualisation: a rerun recording of a registration run (`make_recorder`)."""

from mvreg.viz.colors import residual_colors, scan_colors, viridis
from mvreg.viz.inspect import RecordingFile
from mvreg.viz.recorder import (
    SOLVER_TIMELINE,
    NullRecorder,
    Recorder,
    find_viewer_executable,
    make_blueprint,
    make_recorder,
)

__all__ = [
    "SOLVER_TIMELINE",
    "NullRecorder",
    "Recorder",
    "RecordingFile",
    "find_viewer_executable",
    "make_blueprint",
    "make_recorder",
    "residual_colors",
    "scan_colors",
    "viridis",
]
