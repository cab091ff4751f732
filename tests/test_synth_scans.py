"""Synthesized scans: on the surface within the noise, overlapping, reproducible, checked."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import open3d as o3d
import pytest
import trimesh

from data_synth import (
    PinholeScanner,
    builtin_object,
    generate_scans,
    load_mesh,
    mesh_diagonal,
    synthesize_scans,
)
from mvreg.errors import ConfigError, InputError, OutputExistsError
from mvreg.io.poses import read_poses_json

SHARED_MESHES = ["stanford-bunny.obj", "spot.obj", "fandisk.obj", "cow.obj", "teapot.obj"]


@pytest.fixture(scope="module")
def obj() -> trimesh.Trimesh:
    return builtin_object(seed=0)


class SurfaceDistance:
    """Unsigned distance to a mesh (open3d, float32 around the bounding-box centre)."""

    def __init__(self, mesh: trimesh.Trimesh):
        self.centre = mesh.bounds.mean(axis=0)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(
            o3d.core.Tensor((mesh.vertices - self.centre).astype(np.float32)),
            o3d.core.Tensor(mesh.faces.astype(np.uint32)),
        )

    def __call__(self, points: np.ndarray) -> np.ndarray:
        query = o3d.core.Tensor((points - self.centre).astype(np.float32))
        return self.scene.compute_distance(query).numpy().astype(np.float64)


def _read_world_points(out_dir) -> dict[str, np.ndarray]:
    """Read every scan back with open3d and move it to the world with ground_truth.json."""
    poses = read_poses_json(out_dir / "ground_truth.json")
    world = {}
    for name, T_world_scan in poses.items():
        points = np.asarray(o3d.io.read_point_cloud(str(out_dir / name)).points)
        world[name] = points @ T_world_scan[:3, :3].T + T_world_scan[:3, 3]
    return world


@pytest.mark.parametrize("scanner", ["pinhole", "lidar"])
def test_points_lie_on_the_surface_within_the_noise(tmp_path, obj, scanner):
    noise = 0.003
    result = synthesize_scans(
        obj, tmp_path, views=6, noise=noise, seed=3, scanner=scanner, points_per_scan=4000
    )
    sigma = noise * result.object_diagonal
    d = SurfaceDistance(obj)(np.concatenate(list(_read_world_points(tmp_path).values())))
    assert len(d) > 15_000
    # Range noise moves a point along its ray by N(0, sigma^2): its distance to the surface
    # is at most that (less at oblique incidence), and not much less on average.
    rms = float(np.sqrt(np.mean(d**2)))
    assert 0.4 * sigma < rms < 1.05 * sigma
    assert np.mean(d < 3.0 * sigma) > 0.99
    assert d.max() < 6.0 * sigma


@pytest.mark.parametrize("random_frames", [False, True])
def test_zero_noise_scans_lie_on_the_surface(tmp_path, obj, random_frames):
    result = synthesize_scans(
        obj,
        tmp_path,
        views=4,
        noise=0.0,
        seed=1,
        points_per_scan=3000,
        random_frames=random_frames,
    )
    world = _read_world_points(tmp_path)
    d = SurfaceDistance(obj)(np.concatenate(list(world.values())))
    assert d.max() < 1e-6 * result.object_diagonal
    for scan in result.scans:
        sensor_is_scan_frame = np.allclose(scan.T_world_scan, scan.T_world_sensor)
        assert sensor_is_scan_frame != random_frames


@pytest.mark.parametrize(("scanner", "forward"), [("pinhole", 2), ("lidar", 0)])
def test_scans_are_in_the_sensor_frame(obj, scanner, forward):
    """Sensor at the origin looking along +z (LiDAR: +x, spin axis +z), object in front."""
    scans, _ = generate_scans(obj, views=3, noise=0.0, scanner=scanner, points_per_scan=2000)
    diagonal = mesh_diagonal(obj)
    for scan in scans:
        assert np.all(scan.points[:, forward] > 0.0)
        ranges = np.linalg.norm(scan.points, axis=1)
        assert np.all((ranges > 1.0 * diagonal) & (ranges < 2.0 * diagonal))  # at 1.5 diag
        # The viewing axis points at the object's centre.
        centre_in_sensor = np.linalg.solve(scan.T_world_sensor, [0.0, 0.0, 0.0, 1.0])[:3]
        sideways = np.delete(centre_in_sensor, forward)
        assert sideways == pytest.approx([0.0, 0.0], abs=1e-9)
        R = scan.T_world_sensor[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)


def test_sphere_session_moves_between_neighbouring_views(obj):
    """Consecutive sphere views are neighbours (a hand-held sweep), spread over the sphere."""
    scans, _ = generate_scans(obj, views=12, points_per_scan=200)
    directions = np.array([s.T_world_sensor[:3, 3] for s in scans])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    steps_deg = np.degrees(np.arccos(np.sum(directions[1:] * directions[:-1], axis=1)))
    assert steps_deg.max() < 80.0
    assert directions[:, 2].max() > 0.8 and directions[:, 2].min() < -0.8


@pytest.mark.parametrize("mesh_name", SHARED_MESHES)
def test_every_shared_mesh_whatever_its_units(tmp_path, shared_data, mesh_name):
    path = shared_data / "meshes" / mesh_name
    mesh = load_mesh(path)
    result = synthesize_scans(path, tmp_path, views=4, noise=0.0, points_per_scan=2000)
    diagonal = mesh_diagonal(mesh)
    assert result.object_diagonal == pytest.approx(diagonal)
    d = SurfaceDistance(mesh)(np.concatenate(list(_read_world_points(tmp_path).values())))
    assert d.max() < 1e-6 * diagonal
    counts = np.array(result.point_counts)
    assert 0.5 * 2000 < counts.mean() < 1.5 * 2000
    gt = json.loads((tmp_path / "ground_truth.json").read_text())
    assert gt["format"] == "mvreg.poses/1"
    assert gt["object_diagonal"] == pytest.approx(diagonal)
    assert gt["units"] == "unknown"  # OBJ files do not say
    synth = json.loads((tmp_path / "synth.json").read_text())
    assert synth["mesh"]["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()


def test_adjacent_views_overlap(tmp_path, obj):
    result = synthesize_scans(obj, tmp_path, views=12, noise=0.002, points_per_scan=3000)
    overlap = result.overlap
    assert overlap.shape == (12, 12)
    np.testing.assert_array_equal(np.diag(overlap), 1.0)
    assert np.all((overlap >= 0.0) & (overlap <= 1.0))
    adjacent = np.array(
        [overlap[i, i + 1] for i in range(11)] + [overlap[i + 1, i] for i in range(11)]
    )
    assert adjacent.min() > 0.3
    assert np.median(adjacent) > 0.6
    # Opposite sides of a sphere session share little.
    assert overlap.min() < 0.1
    synth = json.loads((tmp_path / "synth.json").read_text())
    np.testing.assert_array_equal(synth["overlap"]["matrix"], overlap)
    assert synth["point_counts"] == result.point_counts
    assert synth["overlap"]["distance"] >= 0.01 * result.object_diagonal


def test_same_seed_same_bytes_other_seed_other_bytes(tmp_path):
    kwargs = dict(
        views=4,
        noise=0.002,
        outliers=0.02,
        dropout=0.1,
        points_per_scan=2000,
        random_frames=True,
        normals=True,
    )
    runs = {}
    for label, seed in [("a", 5), ("b", 5), ("c", 6)]:
        synthesize_scans("builtin", tmp_path / label, seed=seed, **kwargs)
        runs[label] = {p.name: p.read_bytes() for p in sorted((tmp_path / label).iterdir())}
    assert sorted(runs["a"]) == [
        "ground_truth.json",
        "scan_000.ply",
        "scan_001.ply",
        "scan_002.ply",
        "scan_003.ply",
        "synth.json",
    ]
    assert runs["a"] == runs["b"]
    for name in ["scan_000.ply", "ground_truth.json", "synth.json"]:
        assert runs["a"][name] != runs["c"][name]


def test_ply_is_binary_float64_and_open3d_reads_it_exactly(tmp_path, obj):
    result = synthesize_scans(obj, tmp_path, views=2, points_per_scan=1000, normals=True)
    raw = (tmp_path / "scan_000.ply").read_bytes()
    header, body = raw.split(b"end_header\n", 1)
    assert b"format binary_little_endian 1.0" in header
    assert header.count(b"property double") == 6
    scan = result.scans[0]
    assert len(body) == len(scan.points) * 6 * 8
    cloud = o3d.io.read_point_cloud(str(tmp_path / "scan_000.ply"))
    np.testing.assert_array_equal(np.asarray(cloud.points), scan.points)
    np.testing.assert_array_equal(np.asarray(cloud.normals), scan.normals)
    # Normals face the sensor at the origin.
    assert np.all(np.einsum("ij,ij->i", scan.normals, scan.points) < 0.0)


def test_outliers_and_dropout(obj):
    sigma_rel = 0.001
    scans, _ = generate_scans(
        obj, views=4, noise=sigma_rel, outliers=0.1, seed=2, points_per_scan=4000
    )
    diagonal = mesh_diagonal(obj)
    distance = SurfaceDistance(obj)
    for scan in scans:
        assert scan.is_outlier.mean() == pytest.approx(0.1, abs=0.005)
        d = distance(scan.points_world())
        assert d[~scan.is_outlier].max() < 6.0 * sigma_rel * diagonal
        # Outliers float along their rays: most are far from the surface.
        assert np.mean(d[scan.is_outlier] > 0.01 * diagonal) > 0.7

    # With a fixed sensor, dropout removes its share of the points.
    camera = PinholeScanner(width=120, height=90, fov_x_deg=60.0)
    full, _ = generate_scans(obj, views=3, scanner=camera, seed=4)
    thinned, _ = generate_scans(obj, views=3, scanner=camera, dropout=0.3, seed=4)
    ratio = sum(len(s.points) for s in thinned) / sum(len(s.points) for s in full)
    assert ratio == pytest.approx(0.7, abs=0.03)


@pytest.mark.parametrize("scanner", ["pinhole", "lidar"])
def test_points_per_scan_is_roughly_honoured(obj, scanner):
    for wanted, dropout in [(1500, 0.0), (6000, 0.3)]:
        scans, config = generate_scans(
            obj, views=5, scanner=scanner, points_per_scan=wanted, dropout=dropout
        )
        mean = np.mean([len(s.points) for s in scans])
        assert 0.7 * wanted < mean < 1.3 * wanted, (wanted, mean, config["scanner"])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"views": 0}, "views must be .* not 0"),
        ({"views": -3}, "views must be .* not -3"),
        ({"noise": -0.01}, "noise must be .* not -0.01"),
        ({"noise": float("nan")}, "noise must be"),
        ({"noise": 0.5}, "noise must be .* not 0.5"),
        ({"outliers": 1.5}, "outliers fraction must be .* not 1.5"),
        ({"dropout": -0.1}, "dropout must be .* not -0.1"),
        ({"points_per_scan": 0}, "points per scan must be .* not 0"),
        ({"placement": "spiral"}, "unknown placement 'spiral'"),
        ({"placement": "explicit"}, "explicit placement needs viewpoint positions"),
        ({"scanner": "sonar"}, "unknown scanner 'sonar'"),
        ({"distance": 0.3}, "distance must be .* not 0.3"),
        ({"seed": -1}, "seed must be .* not -1"),
        ({"viewpoints": np.zeros((2, 3))}, "within half a diagonal"),
    ],
)
def test_absurd_parameters_raise_config_error(tmp_path, obj, kwargs, match):
    with pytest.raises(ConfigError, match=match):
        synthesize_scans(obj, tmp_path / "out", **kwargs)
    assert not (tmp_path / "out").exists()  # nothing written before the checks pass


def test_bad_mesh_raises_input_error_naming_the_file(tmp_path):
    with pytest.raises(InputError, match="missing.obj: no such file"):
        synthesize_scans(tmp_path / "missing.obj", tmp_path / "out")


def test_non_empty_output_needs_force(tmp_path, obj):
    out = tmp_path / "out"
    synthesize_scans(obj, out, views=4, points_per_scan=500)
    (out / "notes.txt").write_text("mine")
    with pytest.raises(OutputExistsError, match="not empty"):
        synthesize_scans(obj, out, views=2, points_per_scan=500)
    assert len(list(out.glob("scan_*.ply"))) == 4  # untouched
    synthesize_scans(obj, out, views=2, points_per_scan=500, force=True)
    # Stale scans of the earlier, larger run are gone; other files are kept.
    assert sorted(p.name for p in out.glob("scan_*.ply")) == ["scan_000.ply", "scan_001.ply"]
    assert (out / "notes.txt").read_text() == "mine"
    assert set(read_poses_json(out / "ground_truth.json")) == {"scan_000.ply", "scan_001.ply"}
    a_file = tmp_path / "file"
    a_file.write_text("x")
    with pytest.raises(InputError, match="not a folder"):
        synthesize_scans(obj, a_file, views=2, force=True)


def test_placements(obj):
    diagonal = mesh_diagonal(obj)
    centre = obj.bounds.mean(axis=0)
    for placement in ["sphere", "turntable", "random"]:
        scans, config = generate_scans(
            obj, views=5, placement=placement, points_per_scan=500, seed=1, distance=2.0
        )
        positions = np.array([s.T_world_sensor[:3, 3] for s in scans])
        r = np.linalg.norm(positions - centre, axis=1) / diagonal
        if placement == "random":
            assert np.all((r > 1.6) & (r < 2.4))
        else:
            np.testing.assert_allclose(r, 2.0)
        if placement == "turntable":
            elevation = np.degrees(np.arcsin((positions[:, 2] - centre[2]) / (r * diagonal)))
            np.testing.assert_allclose(elevation, 20.0)
        assert config["placement"] == placement
    explicit = centre + np.array([[3.0, 0.0, 0.0], [0.0, 3.0, 0.0]])
    scans, config = generate_scans(obj, viewpoints=explicit, points_per_scan=500)
    assert config["placement"] == "explicit" and len(scans) == 2
    np.testing.assert_allclose([s.T_world_sensor[:3, 3] for s in scans], explicit)
