"""Ordered range scans (a moving LiDAR): the sequence mode of the pipeline.

Only the sequence's own stages live here: timestamps (:mod:`.timestamps`), odometry
(:mod:`.odometry`), range-scan preprocessing (:mod:`.preprocess`), sequential pairs
(:mod:`.pairs`), loop closures (:mod:`.loops`), pose tracks and their refinement
(:mod:`.tracks`), the drift report (:mod:`.report`); :mod:`.mode` plugs them into
:func:`mvreg.pipeline.register.run_pipeline` as :func:`register_sequence`.
"""

from mvreg.sequence.mode import SequenceMode, SequenceRegistration, register_sequence
from mvreg.sequence.odometry import Odometry, kiss_icp_odometry
from mvreg.sequence.pairs import chain_poses, sequential_pairs
from mvreg.sequence.report import end_to_start_error
from mvreg.sequence.timestamps import (
    TIMESTAMPS_FILE,
    find_gaps,
    read_timestamps_file,
    timestamps_from_names,
)
from mvreg.sequence.tracks import pose_tracks, sequence_tracks_config

__all__ = [
    "TIMESTAMPS_FILE",
    "Odometry",
    "SequenceMode",
    "SequenceRegistration",
    "chain_poses",
    "end_to_start_error",
    "find_gaps",
    "kiss_icp_odometry",
    "pose_tracks",
    "read_timestamps_file",
    "register_sequence",
    "sequence_tracks_config",
    "sequential_pairs",
    "timestamps_from_names",
]
