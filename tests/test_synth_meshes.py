"""Mesh loading: every format trimesh reads, typed errors that name the file."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import trimesh

from data_synth import MeshError, load_mesh, mesh_diagonal
from data_synth.meshes import load_mesh_with_source
from mvreg.errors import InputError

SHARED_MESH_DIAGONALS = {  # from ../shared/data/README.md extents: units differ by 100x
    "stanford-bunny.obj": (0.15, 0.30),
    "spot.obj": (1.5, 3.0),
    "fandisk.obj": (5.0, 10.0),
    "cow.obj": (10.0, 15.0),
    "teapot.obj": (6.0, 10.0),
}


@pytest.mark.parametrize("suffix", ["obj", "ply", "stl", "off", "glb"])
def test_loads_common_formats(tmp_path, suffix):
    box = trimesh.creation.box(extents=[1.0, 2.0, 3.0])
    path = tmp_path / f"box.{suffix}"
    box.export(path)
    mesh = load_mesh(path)
    assert len(mesh.faces) == 12
    assert mesh_diagonal(mesh) == pytest.approx(np.sqrt(14.0))


def test_loads_every_shared_mesh_in_its_own_units(shared_data):
    meshes = sorted(p for p in (shared_data / "meshes").iterdir() if p.suffix.lower() != ".md")
    assert {p.name for p in meshes} >= set(SHARED_MESH_DIAGONALS)
    assert len(meshes) >= 17  # OBJ, PLY and STL: organic, CAD, thin, symmetric
    for path in meshes:
        mesh, source = load_mesh_with_source(path)
        assert len(mesh.faces) > 500, path.name  # the low-poly ones have ~1000 faces
        lo, hi = SHARED_MESH_DIAGONALS.get(path.name, (0.0, np.inf))
        assert lo < mesh_diagonal(mesh) < hi, path.name
        assert len(source.sha256) == 64 and source.name == path.name


def test_in_memory_meshes_and_builtin():
    box = trimesh.creation.box()
    assert len(load_mesh(box).faces) == 12
    o3d_box = o3d.geometry.TriangleMesh.create_box()
    assert len(load_mesh(o3d_box).faces) == 12
    scene = trimesh.Scene([trimesh.creation.box(), trimesh.creation.icosphere(subdivisions=1)])
    assert len(load_mesh(scene).faces) == 12 + 80
    builtin, source = load_mesh_with_source("builtin:2")
    assert source.name == "builtin:2" and len(builtin.faces) > 10_000


def test_missing_file(tmp_path):
    path = tmp_path / "nope.obj"
    with pytest.raises(MeshError, match="nope.obj: no such file"):
        load_mesh(path)


def test_directory_and_empty_file(tmp_path):
    with pytest.raises(MeshError, match="is a directory"):
        load_mesh(tmp_path)
    empty = tmp_path / "empty.obj"
    empty.write_bytes(b"")
    with pytest.raises(MeshError, match="empty.obj: empty file"):
        load_mesh(empty)


@pytest.mark.parametrize(
    ("name", "content", "reason"),
    [
        ("notes.txt", b"hello world\n", "unsupported mesh format"),
        ("garbage.obj", b"hello world\n", "contains no triangle mesh"),
        ("garbage.ply", b"garbage\n", "not a readable mesh"),
        ("points.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n", "point cloud"),
    ],
)
def test_non_mesh_files(tmp_path, name, content, reason):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(MeshError, match=reason) as info:
        load_mesh(path)
    assert name in str(info.value)
    assert isinstance(info.value, InputError)  # the CLI turns it into exit code 2


def test_empty_and_degenerate_meshes():
    with pytest.raises(MeshError, match="no triangles"):
        load_mesh(trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)))
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], process=False)
    with pytest.raises(MeshError, match="zero area"):
        load_mesh(flat)
    nan = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]], [[0, 1, 2]], process=False)
    with pytest.raises(MeshError, match="NaN"):
        load_mesh(nan)


def test_bad_builtin_seed():
    with pytest.raises(MeshError, match="builtin:abc"):
        load_mesh("builtin:abc")
