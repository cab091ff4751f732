"""Load any mesh trimesh reads (OBJ, PLY, STL, OFF, GLB, ...) into a checked ``trimesh.Trimesh``.

Meshes keep their own units (the shared test meshes differ by 100x): nothing here
rescales. Every failure is a :class:`MeshError` naming the file.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from mvreg.errors import InputError

BUILTIN_NAME = "builtin"


class MeshError(InputError):
    """A mesh file is missing, unreadable, not a triangle mesh, empty or degenerate."""

    def __init__(self, source, reason: str):
        self.source = str(source)
        self.reason = reason
        super().__init__(f"{self.source}: {reason}")


@dataclass(frozen=True)
class MeshSource:
    """Where a mesh came from, for provenance in ``synth.json``.

    Attributes:
        name: file name, ``"builtin"`` / ``"builtin:SEED"``, or ``"<in-memory>"``.
        sha256: hex digest of the file bytes; for in-memory and built-in meshes, of the
            float64 vertex and int64 face arrays.
        units: the mesh's units when the file declares them (e.g. ``"m"``), else ``"unknown"``.
    """

    name: str
    sha256: str
    units: str


def file_sha256(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def mesh_sha256(mesh: trimesh.Trimesh) -> str:
    """Hex SHA-256 of a mesh's float64 vertices and int64 faces (for in-memory meshes)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(mesh.vertices, dtype="<f8").tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype="<i8").tobytes())
    return h.hexdigest()


def mesh_diagonal(mesh: trimesh.Trimesh) -> float:
    """Length of the axis-aligned bounding box diagonal, in the mesh's units."""
    lo, hi = mesh.bounds
    return float(np.linalg.norm(hi - lo))


def load_mesh(mesh_or_path) -> trimesh.Trimesh:
    """Load and check a triangle mesh.

    Args:
        mesh_or_path: a path to any file trimesh reads, ``"builtin"`` or ``"builtin:SEED"``
            (the procedural object of :func:`data_synth.builtin_object`), a
            ``trimesh.Trimesh`` / ``trimesh.Scene``, or an ``open3d.geometry.TriangleMesh``.
    Returns:
        ``trimesh.Trimesh`` with (V, 3) float64 vertices and (F, 3) int64 faces, unused
        and degenerate triangles removed. The input object is not modified.
    Raises:
        MeshError: missing file, unreadable or unsupported file, a point cloud or other
            non-mesh, no triangles, NaN/inf vertices, zero extent.
    """
    mesh, _ = load_mesh_with_source(mesh_or_path)
    return mesh


def load_mesh_with_source(mesh_or_path) -> tuple[trimesh.Trimesh, MeshSource]:
    """Like :func:`load_mesh`, also returning the :class:`MeshSource` (name, hash, units)."""
    if isinstance(mesh_or_path, str) and _is_builtin_spec(mesh_or_path):
        from data_synth.builtin import builtin_object

        seed = _builtin_seed(mesh_or_path)
        mesh = builtin_object(seed=seed)
        name = BUILTIN_NAME if seed == 0 else f"{BUILTIN_NAME}:{seed}"
        return mesh, MeshSource(name, mesh_sha256(mesh), "unitless")
    if isinstance(mesh_or_path, str | os.PathLike):
        return _load_file(Path(mesh_or_path))
    mesh = _to_trimesh(mesh_or_path, "<in-memory>")
    mesh = _check(mesh, "<in-memory>")
    return mesh, MeshSource("<in-memory>", mesh_sha256(mesh), _units(mesh))


def _is_builtin_spec(text: str) -> bool:
    return text == BUILTIN_NAME or text.startswith(BUILTIN_NAME + ":")


def _builtin_seed(text: str) -> int:
    if text == BUILTIN_NAME:
        return 0
    seed_text = text.split(":", 1)[1]
    try:
        seed = int(seed_text)
    except ValueError:
        raise MeshError(
            text, f"the built-in object seed must be an integer, not {seed_text!r}"
        ) from None
    if seed < 0:
        raise MeshError(text, f"the built-in object seed must be >= 0, not {seed}")
    return seed


def _load_file(path: Path) -> tuple[trimesh.Trimesh, MeshSource]:
    if not path.exists():
        raise MeshError(path, "no such file")
    if path.is_dir():
        raise MeshError(path, "is a directory, not a mesh file")
    if path.stat().st_size == 0:
        raise MeshError(path, "empty file")
    try:
        loaded = trimesh.load(str(path))
    except NotImplementedError as e:
        raise MeshError(path, f"unsupported mesh format ({e})") from None
    except Exception as e:  # trimesh raises many types on corrupt files
        raise MeshError(path, f"not a readable mesh ({type(e).__name__}: {e})") from None
    mesh = _check(_to_trimesh(loaded, path), path)
    return mesh, MeshSource(path.name, file_sha256(path), _units(loaded))


def _to_trimesh(obj, source) -> trimesh.Trimesh:
    if isinstance(obj, trimesh.Trimesh):
        return obj.copy()
    if isinstance(obj, trimesh.Scene):
        meshes = [g for g in obj.geometry.values() if isinstance(g, trimesh.Trimesh)]
        if not meshes:
            raise MeshError(source, "contains no triangle mesh (empty or not a mesh file)")
        geometry = obj.to_geometry()
        if not isinstance(geometry, trimesh.Trimesh):
            raise MeshError(source, "contains no triangle mesh (empty or not a mesh file)")
        return geometry
    if isinstance(obj, trimesh.PointCloud):
        raise MeshError(source, "is a point cloud without faces, not a triangle mesh")
    if hasattr(obj, "triangles") and hasattr(obj, "vertices"):  # open3d TriangleMesh
        vertices = np.asarray(obj.vertices, dtype=np.float64)
        faces = np.asarray(obj.triangles, dtype=np.int64)
        return trimesh.Trimesh(vertices, faces, process=False)
    raise MeshError(source, f"is a {type(obj).__name__}, not a triangle mesh")


def _check(mesh: trimesh.Trimesh, source) -> trimesh.Trimesh:
    if len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise MeshError(source, "mesh has no triangles")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    if not np.all(np.isfinite(vertices)):
        raise MeshError(source, "mesh has NaN or infinite vertex coordinates")
    faces = np.asarray(mesh.faces, dtype=np.int64)
    # Degenerate (zero-area) triangles cannot be hit and only confuse normals.
    areas = trimesh.triangles.area(vertices[faces])
    keep = areas > 0.0
    if not np.any(keep):
        raise MeshError(source, "every triangle has zero area")
    out = trimesh.Trimesh(vertices, faces[keep], process=False)
    out.remove_unreferenced_vertices()
    if mesh_diagonal(out) <= 0.0:
        raise MeshError(source, "mesh has zero extent")
    return out


def _units(obj) -> str:
    units = getattr(obj, "units", None)
    return str(units) if units else "unknown"
