"""The built-in object: deterministic, closed, and without rotational or mirror symmetry."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import trimesh
from scipy.spatial import cKDTree

from data_synth import builtin_object
from data_synth.builtin import BUILTIN_SIZE
from mvreg.geometry import random_rotations, rotation_angle_deg


@pytest.fixture(scope="module")
def obj() -> trimesh.Trimesh:
    return builtin_object(seed=0)


def _surface_samples(mesh: trimesh.Trimesh, n: int, seed: int) -> np.ndarray:
    points, _ = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(points, dtype=np.float64)


def _chamfer(p: np.ndarray, q: np.ndarray, tree_q: cKDTree | None = None) -> float:
    """Symmetric mean nearest-neighbour distance between (N, 3) and (M, 3) point sets."""
    tree_q = tree_q or cKDTree(q)
    return 0.5 * (tree_q.query(p)[0].mean() + cKDTree(p).query(q)[0].mean())


def _icp(source: np.ndarray, target: np.ndarray, init: np.ndarray, max_dist: float) -> np.ndarray:
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source))
    dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target))
    result = o3d.pipelines.registration.registration_icp(
        src,
        dst,
        max_dist,
        init,
        o3d.pipelines.registration.TransformationEstimationPointToPoint(),
        o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=50),
    )
    return np.asarray(result.transformation)


def test_same_seed_same_mesh_other_seed_other_mesh(obj):
    again = builtin_object(seed=0)
    assert np.array_equal(obj.vertices, again.vertices)
    assert np.array_equal(obj.faces, again.faces)
    other = builtin_object(seed=1)
    assert np.abs(other.vertices - obj.vertices).max() > 0.05 * BUILTIN_SIZE


def test_closed_oriented_and_sized(obj):
    assert obj.is_watertight and obj.is_winding_consistent
    assert obj.volume > 0.0  # outward normals
    assert np.max(obj.extents) == pytest.approx(BUILTIN_SIZE)
    np.testing.assert_allclose(obj.bounds.mean(axis=0), 0.0, atol=1e-12)
    # Three different extents: no two axes of the bounding box are interchangeable.
    e = np.sort(obj.extents)
    assert e[1] / e[0] > 1.1 and e[2] / e[1] > 1.1


def test_has_fine_and_coarse_detail(obj):
    # Fine detail: the normals of neighbouring faces vary (ripples, not a smooth blob) ...
    angles = np.degrees(obj.face_adjacency_angles)
    assert np.percentile(angles, 90) > 2.0
    # ... coarse detail: the radius varies by tens of percent (horns, lobes, dents).
    radius = np.linalg.norm(obj.vertices - obj.centroid, axis=1)
    assert radius.max() / np.median(radius) > 1.5


def test_no_rotational_symmetry(obj):
    """Rotated by >= 20 degrees about its centroid, the object is far from itself."""
    a = _surface_samples(obj, 8000, seed=1)
    centroid = a.mean(axis=0)
    a -= centroid
    b = _surface_samples(obj, 8000, seed=2) - centroid
    tree_a = cKDTree(a)
    spacing = float(np.mean(tree_a.query(a, k=2)[0][:, 1]))
    # The same surface sampled twice is about one spacing apart: the scale to beat.
    assert _chamfer(b, a, tree_a) < 1.3 * spacing

    rotations = random_rotations(np.random.default_rng(7), 120, 3)
    rotations = rotations[rotation_angle_deg(rotations) >= 20.0][:40]
    assert len(rotations) == 40
    distances = [_chamfer(b @ r.T, a, tree_a) for r in rotations]
    assert min(distances) > 4.0 * spacing

    # Local refinement cannot find another self-alignment either: ICP from 12 random
    # starts ends at the identity or well away from the surface.
    sub = a[::8]
    for r in random_rotations(np.random.default_rng(8), 12, 3):
        init = np.eye(4)
        init[:3, :3] = r
        t = _icp(sub, sub, init, 0.3 * BUILTIN_SIZE)
        if rotation_angle_deg(t[:3, :3]) < 5.0:
            continue
        moved = b @ t[:3, :3].T + t[:3, 3]
        assert _chamfer(moved, a, tree_a) > 3.0 * spacing


def test_no_mirror_symmetry(obj):
    """Its mirror image, however rotated and refined by ICP, stays far from the object."""
    a = _surface_samples(obj, 8000, seed=1)
    a -= a.mean(axis=0)
    tree_a = cKDTree(a)
    spacing = float(np.mean(tree_a.query(a, k=2)[0][:, 1]))
    mirrored = a * np.array([-1.0, 1.0, 1.0])  # any plane: rotations cover the rest
    sub, sub_mirrored = a[::8], mirrored[::8]
    best = np.inf
    for r in random_rotations(np.random.default_rng(9), 12, 3):
        init = np.eye(4)
        init[:3, :3] = r
        t = _icp(sub_mirrored, sub, init, 0.3 * BUILTIN_SIZE)
        best = min(best, _chamfer(mirrored @ t[:3, :3].T + t[:3, 3], a, tree_a))
    assert best > 3.0 * spacing


def test_symmetry_check_detects_a_symmetric_shape():
    """Control: the mirror test on an ellipsoid finds its symmetry (about one spacing)."""
    ellipsoid = trimesh.creation.icosphere(subdivisions=4).apply_scale([1.0, 0.7, 0.5])
    a = _surface_samples(ellipsoid, 4000, seed=1)
    a -= a.mean(axis=0)
    tree_a = cKDTree(a)
    spacing = float(np.mean(tree_a.query(a, k=2)[0][:, 1]))
    mirrored = a * np.array([-1.0, 1.0, 1.0])
    t = _icp(mirrored[::4], a[::4], np.eye(4), 0.3)
    assert _chamfer(mirrored @ t[:3, :3].T + t[:3, 3], a, tree_a) < 1.5 * spacing
