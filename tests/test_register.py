"""`mvreg register` end to end: accuracy on the real bunny scans, outputs, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from mvreg.cli import app
from mvreg.io.poses import read_poses_json, read_poses_kitti, read_poses_tum
from mvreg.metrics import pose_errors
from tests.conftest import require_shared

runner = CliRunner()


def bunny_truth(folder: Path) -> dict[str, np.ndarray]:
    """bun.conf: p_world = R(q)^T p + t, q = (qx, qy, qz, qw) (see shared/data/README.md)."""
    truth = {}
    for line in (folder / "bun.conf").read_text().splitlines():
        p = line.split()
        if not p or p[0] != "bmesh":
            continue
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat([float(v) for v in p[5:9]]).as_matrix().T
        T[:3, 3] = [float(v) for v in p[2:5]]
        truth[p[1]] = T
    return truth


@pytest.fixture(scope="module")
def bunny_run(tmp_path_factory):
    folder = require_shared() / "stanford_bunny_scans"
    out = tmp_path_factory.mktemp("bunny") / "out"
    r = runner.invoke(app, ["register", str(folder), "--out", str(out), "--seed", "0"])
    assert r.exit_code == 0, r.output
    return folder, out


def test_bunny_all_registered_within_targets(bunny_run):
    folder, out = bunny_run
    est = read_poses_json(out / "poses.json")
    truth = bunny_truth(folder)
    assert sorted(est) == sorted(truth)
    names = sorted(truth)
    err = pose_errors(np.stack([est[n] for n in names]), np.stack([truth[n] for n in names]))
    # Issue targets: rotation max <= 0.3 deg, translation max <= 0.6 mm against bun.conf.
    assert err.rotation_deg.max() <= 0.3, err.rotation_deg
    assert err.translation.max() <= 0.6e-3, err.translation
    report = json.loads((out / "report.json").read_text())
    assert report["unregistered"] == []
    assert report["certificate"]["certified"] is True
    # Every real scan verified (the run exits 0 only so; asserted here, not only implied).
    ver = report["verification"]["scans"]
    assert sorted(ver) == names and all(v["status"] == "verified" for v in ver.values()), ver
    # Overlap residual no larger than that of bun.conf's own alignment (same metric).
    ours = report["overlap_residual"]["mean"]
    assert ours > 0


def test_bunny_overlap_residual_matches_reference(bunny_run):
    """Mean nearest-neighbour distance between overlapping scans, ours vs bun.conf's.

    Compared on the same points: those within 0.5 mm of another scan under both alignments
    (a better alignment brings more points under the threshold, near it, which would raise
    an unpaired mean; see docs/benchmarks/register.md for both).
    """
    from scipy.spatial import cKDTree

    from mvreg.geometry import transform_points
    from mvreg.io.loaders import load_scan

    folder, out = bunny_run
    est = read_poses_json(out / "poses.json")
    truth = bunny_truth(folder)
    names = sorted(truth)
    pts = {n: load_scan(folder / n).points for n in names}

    def nn_dist(poses):
        world = [transform_points(poses[n], pts[n]) for n in names]
        trees = [cKDTree(w) for w in world]
        out = []
        for i, w in enumerate(world):
            q = w[::3]  # every third point queried against the full other scans
            best = np.full(len(q), np.inf)
            for j, t in enumerate(trees):
                if j != i:
                    best = np.minimum(best, t.query(q, distance_upper_bound=1e-3)[0])
            out.append(best)
        return np.concatenate(out)

    a, b = nn_dist(est), nn_dist(truth)
    both = (a < 0.5e-3) & (b < 0.5e-3)
    assert both.mean() > 0.85
    assert a[both].mean() <= 1.005 * b[both].mean(), (a[both].mean(), b[both].mean())
    assert 0.2e-3 < np.median(b[b < 0.5e-3]) < 0.3e-3  # the data README's 0.23-0.29 mm


def test_outputs_parse_back(bunny_run):
    import open3d as o3d

    from mvreg.viz import RecordingFile

    _, out = bunny_run
    est = read_poses_json(out / "poses.json")
    names = list(est)
    _, tum = read_poses_tum(out / "poses_tum.txt")
    kitti = read_poses_kitti(out / "poses_kitti.txt")
    for n, a, b in zip(names, tum, kitti, strict=True):
        assert np.allclose(a, est[n], atol=1e-12)
        assert np.array_equal(b, est[n])  # full precision round trip
    assert np.allclose(est[names[0]], np.eye(4), atol=1e-12)  # first scan = world frame
    cloud = o3d.io.read_point_cloud(str(out / "merged.ply"))
    assert len(cloud.points) > 10_000 and cloud.has_colors()
    report = json.loads((out / "report.json").read_text())
    assert report["config"]["seed"] == 0 and report["voxel_size"] > 0
    assert len(report["pairs"]) == 45 and {"final_weight", "overlap_ratio"} <= set(
        report["pairs"][0]
    )
    # The joint ICP ran after the certified solve, and both files say how far it moved.
    j = report["joint_icp"]
    assert (
        j["accepted"] and 1 <= j["iterations"] <= report["config"]["refine"]["joint_icp_iterations"]
    )
    assert 0 < j["max_rotation_change_deg"] < 0.5 and j["max_point_move_voxels"] <= 1.0
    assert j["residual_median_end"] <= j["residual_median_start"]
    moved = json.loads((out / "poses.json").read_text())["moved_after_certificate"]
    assert moved["max_rotation_deg"] == j["max_rotation_change_deg"]
    rec = RecordingFile(out / "recording.rrd")
    assert rec.has("world/scans/bun000.ply")
    assert sum(e.startswith("/raw/") for e in rec.entities) == 10
    assert rec.has("residual_heatmap/merged")
    assert any(e.startswith("/world/pairs/") for e in rec.entities)  # per-pair correspondences
    steps, values = rec.scalars("solver/objective", "solver_iteration")
    assert len(steps) >= 2 and np.all(np.isfinite(values))  # one point per global solve at least
    assert not list(out.glob(".*"))  # no temporary files left behind


def test_refuses_to_overwrite_without_force(bunny_run):
    folder, out = bunny_run
    r = runner.invoke(app, ["register", str(folder), "--out", str(out)])
    assert r.exit_code == 2
    assert "--force" in r.output


def _few_bunny_scans(tmp_path: Path, names=("bun000.ply", "bun045.ply", "bun315.ply")) -> Path:
    from mvreg.io.loaders import load_scan

    folder = require_shared() / "stanford_bunny_scans"
    d = tmp_path / "scans"
    d.mkdir()
    for n in names:
        np.save(d / (Path(n).stem + ".npy"), load_scan(folder / n).points[::2])
    return d


def _register_synthetic_within_target(tmp_path: Path, mesh: str, noise: float):
    """data_synth scans of a shared mesh (12 views, seed 0, random frames), registered
    with defaults: every scan registered and within the issue's 0.5 deg / 0.5% target
    (translation at the scan centroids, as issue 13 and the generalization benchmark
    measure it: at the random frames' origins, far from the object, a rotation error's
    lever arm adds to it)."""
    from data_synth import synthesize_scans
    from mvreg.pipeline import register

    folder = tmp_path / mesh
    path = require_shared() / "meshes" / f"{mesh}.obj"
    synth = synthesize_scans(path, folder, views=12, noise=noise, seed=0, random_frames=True)
    reg = register(folder, seed=0)
    assert not reg.unregistered
    e = reg.truth_errors
    assert e["rotation_deg_max"] < 0.5, e
    assert e["translation_at_centroid_max"] < 0.005 * synth.object_diagonal, e
    return reg


def test_near_symmetric_teapot_within_target(tmp_path):
    """The teapot's body is a body of revolution: pairs flipped about its axis fit well and
    used to win (seed 0 had three). Every scan within the issue's target."""
    reg = _register_synthetic_within_target(tmp_path, "teapot", noise=0.002)
    assert not reg.report()["bad_pairs"]


def test_noise_free_cad_scans_register(tmp_path):
    """Noise-free scans of a CAD part: the scans' noise estimate goes to zero there, and
    before it had a floor every correct fandisk pair failed the residual test (0 of 12
    registered)."""
    _register_synthetic_within_target(tmp_path, "fandisk", noise=0.0)


def test_same_seed_same_poses(tmp_path):
    scans = _few_bunny_scans(tmp_path)
    outs = []
    for k in range(2):
        r = runner.invoke(
            app,
            ["register", str(scans), "--out", str(tmp_path / f"o{k}"), "--no-rrd", "--seed", "3"],
        )
        assert r.exit_code == 0, r.output
        outs.append(read_poses_json(tmp_path / f"o{k}" / "poses.json"))
    for n in outs[0]:
        assert np.array_equal(outs[0][n], outs[1][n])


def test_a_run_computes_blas_on_one_thread(tmp_path):
    """Inside a run, BLAS uses one thread whatever the process allows, and the process's
    limit is back after it: OpenBLAS splits products by its thread count, so sums round
    differently with another count, and the 60-station scene registered 39 scans with
    OpenBLAS's two threads where one thread gave 47 (docs/benchmarks/scale.md)."""
    threadpoolctl = pytest.importorskip("threadpoolctl")
    from mvreg import register

    def blas_threads():
        info = [p for p in threadpoolctl.threadpool_info() if p["user_api"] == "blas"]
        return {p["num_threads"] for p in info}

    seen = []

    def hook(pre, results):
        seen.append(blas_threads())
        return results

    with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
        before = blas_threads()
        if not before:
            pytest.skip("no BLAS library found by threadpoolctl")
        register(_few_bunny_scans(tmp_path), seed=0, pair_hook=hook)
        assert blas_threads() == before
    assert seen == [{1}]


def test_scan_without_overlap_is_reported_unregistered(tmp_path):
    scans = _few_bunny_scans(tmp_path)
    rng = np.random.default_rng(0)
    np.save(scans / "zz_noise.npy", rng.uniform(-1, 1, size=(5000, 3)) * [0.1, 0.1, 0.001] + 5.0)
    out = tmp_path / "out"
    r = runner.invoke(app, ["register", str(scans), "--out", str(out), "--no-rrd"])
    assert r.exit_code == 3, r.output
    report = json.loads((out / "report.json").read_text())
    assert report["unregistered"] == ["zz_noise.npy"]
    assert "zz_noise.npy" not in read_poses_json(out / "poses.json")


@pytest.mark.parametrize(
    ("setup", "message"),
    [
        ("empty_folder", "no scan files"),
        ("single_scan", "at least 2 scans"),
        ("empty_file", "empty.ply"),
        ("corrupt_ply", "corrupt.ply"),
        ("nan_only", "nan.npy"),
    ],
)
def test_bad_input_gives_one_line_and_exit_2(tmp_path, setup, message):
    d = tmp_path / "in"
    d.mkdir()
    good = np.random.default_rng(0).uniform(size=(500, 3))
    if setup == "single_scan":
        np.save(d / "a.npy", good)
    elif setup == "empty_file":
        np.save(d / "a.npy", good)
        (d / "empty.ply").write_bytes(b"")
    elif setup == "corrupt_ply":
        np.save(d / "a.npy", good)
        (d / "corrupt.ply").write_bytes(
            b"ply\nformat ascii 1.0\nelement vertex 10\nproperty float x\nend_header\n1 2\n"
        )
    elif setup == "nan_only":
        np.save(d / "a.npy", good)
        np.save(d / "nan.npy", np.full((500, 3), np.nan))
    r = runner.invoke(app, ["register", str(d), "--out", str(tmp_path / "out")])
    assert r.exit_code == 2, r.output
    assert message in r.output
    assert "Traceback" not in r.output
    assert not (tmp_path / "out" / "poses.json").exists()


def test_absurd_parameters(tmp_path):
    d = _few_bunny_scans(tmp_path)
    r = runner.invoke(app, ["register", str(d), "--out", str(tmp_path / "o"), "--solver", "magic"])
    assert r.exit_code == 2 and "unknown solver" in r.output
    r = runner.invoke(app, ["register", str(d), "--out", str(tmp_path / "o"), "--voxel-size", "0"])
    assert r.exit_code == 2


def test_translation_error_at_the_centroid_ignores_where_the_frame_origin_is():
    """A 0.3 degree turn of a scan about its own centroid moves its points little, but
    moves a frame origin three object sizes away by 1.6% of the object size."""
    from mvreg.geometry import make_transform

    rng = np.random.default_rng(0)
    T_true = np.stack(
        [make_transform(Rotation.random(random_state=rng).as_matrix(), 0) for _ in range(4)]
    )
    centroids = rng.normal(scale=3.0, size=(4, 3))  # local frames: origin ~3 units from the data
    centroids[3] = [3.0, 0.0, 0.0]
    turn = make_transform(Rotation.from_rotvec([0, 0, np.radians(0.3)]).as_matrix(), 0)
    about = make_transform(np.eye(3), centroids[3])
    T_est = T_true.copy()
    T_est[3] = T_true[3] @ about @ turn @ np.linalg.inv(about)
    at_origin = pose_errors(T_est, T_true).translation
    at_centroid = pose_errors(T_est, T_true, at=centroids).translation
    # 3 * 0.3 deg in radians = 0.0157 at the origin, shared with the others by the gauge
    assert at_origin[3] > 0.01
    assert at_centroid[3] < 0.3 * at_origin[3]


def test_a_far_stray_point_is_dropped_at_load():
    """Issue 16: one stray point per scan at 1e9 broke the run (exit 4, Open3D's voxel grid
    too large); the load stage drops far strays and counts them, and leaves scans without
    any untouched (same object)."""
    from mvreg.io.loaders import Scan
    from mvreg.pipeline.load import drop_far_strays

    rng = np.random.default_rng(0)
    pts = rng.normal(size=(500, 3))
    scan = Scan(name="s", path=Path("s.npy"), points=np.vstack([pts, [[1e9, 1e9, 1e9]]]))
    out = drop_far_strays(scan, 100)
    assert out.num_dropped_far == 1 and np.array_equal(out.points, pts)
    clean = Scan(name="c", path=Path("c.npy"), points=pts)
    assert drop_far_strays(clean, 100) is clean


def test_keyword_overrides_apply_on_top_of_a_given_config(tmp_path):
    """register(config=cfg, seed=3) runs with cfg's settings and seed 3 (the keywords were
    silently dropped when a config was given)."""
    from mvreg.config import RegisterConfig, load_config
    from mvreg.errors import ConfigError
    from mvreg.pipeline import register

    cfg = RegisterConfig()
    cfg.refine.last_round_correspondences = "nearest"
    reg = register(_few_bunny_scans(tmp_path), config=cfg, seed=3, **{"refine.rounds": 2})
    assert reg.config.seed == 3 and reg.config.refine.rounds == 2
    assert reg.config.refine.last_round_correspondences == "nearest"
    assert cfg.seed == 0 and cfg.refine.rounds == 3  # the caller's object is not changed
    with pytest.raises(ConfigError, match="not both"):
        load_config(tmp_path / "c.json", base=cfg)
