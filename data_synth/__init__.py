"""Synthetic test data with ground truth: realistic partial scans of meshes.

One call::

    from data_synth import synthesize_scans
    result = synthesize_scans("builtin", "scans/", views=12, noise=0.002, seed=0)

and the staged pieces underneath: :func:`load_mesh`, :func:`builtin_object`,
:func:`make_viewpoints`, the scanners (:class:`PinholeScanner`, :class:`LidarScanner`,
:func:`simulate_scan`), :func:`generate_scans` (in memory), :func:`write_ply`, and
:func:`synthesize_sequence` for an ordered LiDAR sequence through a scene.
"""

from __future__ import annotations

import importlib

# Lazy re-exports: importing a sibling (data_synth.problems) must not pull trimesh/open3d.
_EXPORTS = {
    "builtin_object": "data_synth.builtin",
    "MeshError": "data_synth.meshes",
    "load_mesh": "data_synth.meshes",
    "mesh_diagonal": "data_synth.meshes",
    "Viewpoints": "data_synth.placement",
    "look_at": "data_synth.placement",
    "make_viewpoints": "data_synth.placement",
    "LidarScanner": "data_synth.scanner",
    "MeshRaycaster": "data_synth.scanner",
    "NoiseModel": "data_synth.scanner",
    "PinholeScanner": "data_synth.scanner",
    "RawScan": "data_synth.scanner",
    "simulate_scan": "data_synth.scanner",
    "SynthResult": "data_synth.scans",
    "SynthScan": "data_synth.scans",
    "generate_scans": "data_synth.scans",
    "overlap_matrix": "data_synth.scans",
    "ply_bytes": "data_synth.scans",
    "read_synth_json": "data_synth.scans",
    "synthesize_scans": "data_synth.scans",
    "write_ply": "data_synth.scans",
    "Scene": "data_synth.sequence",
    "SequenceResult": "data_synth.sequence",
    "build_scene": "data_synth.sequence",
    "synthesize_sequence": "data_synth.sequence",
}


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'data_synth' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))


__all__ = [
    "LidarScanner",
    "MeshError",
    "MeshRaycaster",
    "NoiseModel",
    "PinholeScanner",
    "RawScan",
    "Scene",
    "SequenceResult",
    "SynthResult",
    "SynthScan",
    "Viewpoints",
    "build_scene",
    "builtin_object",
    "generate_scans",
    "load_mesh",
    "look_at",
    "make_viewpoints",
    "mesh_diagonal",
    "overlap_matrix",
    "ply_bytes",
    "read_synth_json",
    "simulate_scan",
    "synthesize_scans",
    "synthesize_sequence",
    "write_ply",
]
