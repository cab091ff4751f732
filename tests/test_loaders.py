"""Scan loaders: every format round-trips, every bad file is named in its error."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from mvreg.errors import InputError, ScanFileError
from mvreg.io.loaders import (
    Scan,
    ScanLoader,
    list_scan_files,
    load_scan,
    load_scans,
    natural_key,
    register_loader,
    supported_suffixes,
)
from mvreg.io.loaders.base import RawCloud


def _cloud(n: int = 200, seed: int = 0):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(n, 3)) * [1.0, 2.0, 0.5] + [10.0, -3.0, 7.0]
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    colors = rng.uniform(size=(n, 3))
    return points, normals, colors


def _write_o3d(path: Path, points, normals=None, colors=None, **kwargs) -> Path:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if normals is not None:
        pcd.normals = o3d.utility.Vector3dVector(normals)
    if colors is not None:
        pcd.colors = o3d.utility.Vector3dVector(colors)
    assert o3d.io.write_point_cloud(str(path), pcd, **kwargs)
    return path


# (suffix, has normals, has colors, float tolerance of the format)
FORMATS = [
    (".ply", True, True, 1e-12),
    (".pcd", True, True, 1e-5),  # open3d writes PCD as float32
    (".xyz", False, False, 1e-8),
    (".xyzn", True, False, 1e-8),
    (".xyzrgb", False, True, 1e-8),
    (".pts", False, True, 1e-8),
]


@pytest.mark.parametrize(("suffix", "has_normals", "has_colors", "tol"), FORMATS)
def test_open3d_formats_round_trip(tmp_path, suffix, has_normals, has_colors, tol):
    points, normals, colors = _cloud()
    path = _write_o3d(tmp_path / f"scan{suffix}", points, normals, colors)
    scan = load_scan(path)
    assert isinstance(scan, Scan)
    assert scan.name == f"scan{suffix}" and scan.path == path
    assert scan.points.shape == (200, 3) and scan.points.dtype == np.float64
    np.testing.assert_allclose(scan.points, points, atol=tol * 20)
    assert (scan.normals is not None) == has_normals
    if has_normals:
        np.testing.assert_allclose(scan.normals, normals, atol=1e-5)
    assert (scan.colors is not None) == has_colors
    if has_colors:
        np.testing.assert_allclose(scan.colors, colors, atol=1 / 255 + 1e-6)
    assert scan.num_dropped_nonfinite == 0


def test_binary_ply_and_pcd_round_trip(tmp_path):
    points, _, _ = _cloud()
    for suffix in (".ply", ".pcd"):
        path = _write_o3d(tmp_path / f"bin{suffix}", points, write_ascii=False)
        np.testing.assert_allclose(load_scan(path).points, points, atol=1e-4)


def test_npy_variants(tmp_path):
    points, normals, colors = _cloud()
    np.save(tmp_path / "a.npy", points)
    np.save(tmp_path / "b.npy", np.hstack([points, normals]))
    np.save(tmp_path / "c.npy", np.hstack([points, colors * 255.0]))
    np.save(tmp_path / "d.npy", np.hstack([points, colors]).astype(np.float32))
    a, b, c, d = (load_scan(tmp_path / f"{k}.npy") for k in "abcd")
    np.testing.assert_array_equal(a.points, points)
    assert a.normals is None and a.colors is None
    np.testing.assert_array_equal(b.normals, normals)
    assert b.colors is None
    np.testing.assert_allclose(c.colors, colors)
    assert c.normals is None
    np.testing.assert_allclose(d.colors, colors, atol=1e-6)


def test_nan_rows_are_dropped_and_counted(tmp_path):
    points, _, _ = _cloud()
    points[[3, 50, 51]] = np.nan
    points[7, 2] = np.inf
    np.save(tmp_path / "holes.npy", points)
    scan = load_scan(tmp_path / "holes.npy")
    assert scan.num_points == 196 and scan.num_dropped_nonfinite == 4
    assert np.all(np.isfinite(scan.points))
    assert "dropped_nonfinite=4" in repr(scan)
    (tmp_path / "holes.xyz").write_text("nan nan nan\n" + "".join(f"{i} 1 2\n" for i in range(150)))
    scan = load_scan(tmp_path / "holes.xyz")
    assert scan.num_points == 150 and scan.num_dropped_nonfinite == 1


def _ply_header(n: int, fmt: str = "ascii") -> str:
    return (
        f"ply\nformat {fmt} 1.0\nelement vertex {n}\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    )


BAD_FILES = {
    "empty.ply": (b"", "empty file"),
    "truncated.ply": (
        (_ply_header(300) + "".join(f"{i} 1 2\n" for i in range(120)) + "4 5\n").encode(),
        "truncated PLY",
    ),
    "cut_line.ply": (
        (_ply_header(150) + "".join(f"{i} 1 2\n" for i in range(149)) + "4 5").encode(),
        "incomplete",
    ),
    "truncated_binary.ply": (
        _ply_header(300, "binary_little_endian").encode() + np.zeros((100, 3), "<f4").tobytes(),
        "truncated PLY",
    ),
    "garbage.ply": (b"\x00\x01garbage" * 64, "not a PLY file"),
    "no_vertices.ply": (_ply_header(0).encode(), "no vertices"),
    "header_only.ply": (b"ply\nformat ascii 1.0\nelement vertex 10\n", "corrupt header"),
    "nan_only.xyz": (b"nan nan nan\n" * 300, "NaN"),
    "few.xyz": (b"".join(f"{i} 0 1\n".encode() for i in range(20)), "fewer than the minimum"),
    "unparsable.xyz": (b"hello world\nthis is not a scan\n" * 20, "line 1"),
    "wrong_shape.npy": (None, "expected an (N, 3) or (N, 6)"),
    "not_numpy.npy": (b"this is no npy file" * 10, "not a .npy file"),
    "truncated.pcd": (
        b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 500\n"
        b"HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 500\nDATA binary\n" + bytes(120),
        "truncated PCD",
    ),
}


@pytest.mark.parametrize("name", sorted(BAD_FILES))
def test_bad_files_raise_naming_the_file(tmp_path, name):
    content, reason = BAD_FILES[name]
    path = tmp_path / name
    if content is None:
        np.save(path, np.zeros((300, 4)))
    else:
        path.write_bytes(content)
    with pytest.raises(ScanFileError) as info:
        load_scan(path)
    assert info.value.path == str(path)
    assert str(path) in str(info.value)
    assert reason in info.value.reason


def test_missing_and_unsupported_files(tmp_path):
    with pytest.raises(ScanFileError, match="no such file"):
        load_scan(tmp_path / "missing.ply")
    (tmp_path / "notes.txt").write_text("1 2 3\n")
    with pytest.raises(ScanFileError, match="unsupported file type '.txt'"):
        load_scan(tmp_path / "notes.txt")


def test_min_points_is_configurable(tmp_path):
    points, _, _ = _cloud(30)
    np.save(tmp_path / "small.npy", points)
    with pytest.raises(ScanFileError, match="only 30 valid points"):
        load_scan(tmp_path / "small.npy")
    assert load_scan(tmp_path / "small.npy", min_points=10).num_points == 30


def test_folder_listing_natural_order_ignores_other_files(tmp_path):
    points, _, _ = _cloud()
    for name in ("scan_10.npy", "scan_2.npy", "Scan_1.ply", "scan_9.xyz"):
        path = tmp_path / name
        if path.suffix == ".npy":
            np.save(path, points)
        else:
            _write_o3d(path, points)
    for name in ("ground_truth.json", "synth.json", "timestamps.txt", ".hidden.ply"):
        (tmp_path / name).write_text("{}")
    (tmp_path / "sub.ply").mkdir()
    files = list_scan_files(tmp_path)
    assert [p.name for p in files] == ["Scan_1.ply", "scan_2.npy", "scan_9.xyz", "scan_10.npy"]
    scans = load_scans(tmp_path)
    assert [s.name for s in scans] == [p.name for p in files]
    assert [s.name for s in load_scans(files[:2])] == ["Scan_1.ply", "scan_2.npy"]
    assert sorted(["a10", "a9", "a10b", "A1"], key=natural_key) == ["A1", "a9", "a10", "a10b"]


def test_folder_errors(tmp_path):
    (tmp_path / "readme.txt").write_text("no scans here")
    with pytest.raises(InputError, match="no scan files found") as info:
        load_scans(tmp_path)
    assert str(tmp_path) in str(info.value)
    with pytest.raises(InputError, match="not a folder"):
        list_scan_files(tmp_path / "nope")
    with pytest.raises(InputError, match="no scan files given"):
        load_scans([])


def test_one_bad_file_in_a_folder_is_named(tmp_path):
    points, _, _ = _cloud()
    np.save(tmp_path / "a.npy", points)
    (tmp_path / "b.ply").write_bytes(b"")
    with pytest.raises(ScanFileError) as info:
        load_scans(tmp_path)
    assert info.value.path == str(tmp_path / "b.ply")


def test_pcd_viewpoint_becomes_sensor_origin(tmp_path):
    points, _, _ = _cloud()
    path = tmp_path / "view.pcd"
    body = "".join(f"{x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in points)
    header = (
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {len(points)}\nHEIGHT 1\nVIEWPOINT 1.5 -2 3 1 0 0 0\n"
        f"POINTS {len(points)}\nDATA ascii\n"
    )
    path.write_text(header + body)
    scan = load_scan(path)
    np.testing.assert_allclose(scan.sensor_origin, [1.5, -2.0, 3.0])
    np.testing.assert_allclose(scan.points, points, atol=1e-5)
    # The default viewpoint says nothing about the sensor.
    default = _write_o3d(tmp_path / "default.pcd", points)
    assert load_scan(default).sensor_origin is None


def test_registry_accepts_new_loaders(tmp_path):
    class CsvLoader:
        suffixes = (".csvpts",)

        def read(self, path: Path) -> RawCloud:
            return RawCloud(np.loadtxt(path, delimiter=",").reshape(-1, 3))

    assert isinstance(CsvLoader(), ScanLoader)
    register_loader(CsvLoader())
    try:
        points, _, _ = _cloud()
        np.savetxt(tmp_path / "x.csvpts", points, delimiter=",")
        np.testing.assert_allclose(load_scan(tmp_path / "x.csvpts").points, points)
        assert ".csvpts" in supported_suffixes()
    finally:
        from mvreg.io import loaders

        loaders._REGISTRY.pop(".csvpts", None)
    with pytest.raises(TypeError):
        register_loader(object())


def test_bunny_scans_load(shared_data):
    folder = shared_data / "stanford_bunny_scans"
    scans = load_scans(folder)
    assert [s.name for s in scans][:3] == ["bun000.ply", "bun045.ply", "bun090.ply"]
    assert len(scans) == 10  # bun.conf and README are not scans
    assert all(30000 <= s.num_points <= 41000 for s in scans)
    assert scans[0].num_points == 40256 and scans[0].num_dropped_nonfinite == 0


# ---------------------------------------------------------------- issue 16: hostile files
def _ascii_ply(rows: list[str], n: int | None = None) -> bytes:
    return (_ply_header(len(rows) if n is None else n) + "".join(r + "\n" for r in rows)).encode()


def _rows(k: int = 150) -> list[str]:
    return [f"{i} {i % 7} {i % 11}" for i in range(k)]


@pytest.mark.parametrize(
    ("edit", "reason"),
    [
        (lambda r: r[:40] + ["1 x 2"] + r[41:], "line 48: value 'x' is not a number"),
        (lambda r: r[:40] + ["1 1e999 2"] + r[41:], "line 48: value '1e999' is out of range"),
        (lambda r: r[:40] + ["1 1e39 2"] + r[41:], "'1e39' is out of range"),
        (lambda r: r[:40] + ["1 2"] + r[41:], "line 48: 2 values, the header declares 3"),
        (lambda r: r[:40] + ["1 2 3 4"] + r[41:], "line 48: 4 values"),
    ],
)
def test_corrupt_ascii_ply_names_the_line(tmp_path, edit, reason):
    path = tmp_path / "bad.ply"
    path.write_bytes(_ascii_ply(edit(_rows())))
    with pytest.raises(ScanFileError) as info:
        load_scan(path)
    assert reason in info.value.reason and str(path) in str(info.value)


def test_ascii_ply_literal_nan_is_a_dropped_row_inf_an_error(tmp_path):
    rows = _rows()
    rows[3] = "nan 1 2"
    path = tmp_path / "holes.ply"
    path.write_bytes(_ascii_ply(rows))
    scan = load_scan(path)
    assert scan.num_points == 149 and scan.num_dropped_nonfinite == 1
    rows[4] = "1 -inf 2"
    path.write_bytes(_ascii_ply(rows))
    with pytest.raises(ScanFileError, match="line 12: value '-inf' is out of range"):
        load_scan(path)


@pytest.mark.parametrize(("declared", "held"), [(120, 150), (200, 150)])
def test_vertex_count_must_match_the_file(tmp_path, declared, held):
    path = tmp_path / "count.ply"
    path.write_bytes(_ascii_ply(_rows(held), n=declared))
    with pytest.raises(ScanFileError) as info:
        load_scan(path)
    assert f"declares {declared}" in info.value.reason and f"holds {held}" in info.value.reason


def test_binary_ply_with_extra_bytes_is_refused(tmp_path):
    path = tmp_path / "long.ply"
    path.write_bytes(
        _ply_header(150, "binary_little_endian").encode() + np.ones((160, 3), "<f4").tobytes()
    )
    with pytest.raises(
        ScanFileError, match="declares 150 vertex rows .* holds 1920 data bytes .160 rows"
    ):
        load_scan(path)


def test_all_garbage_files_are_named(tmp_path):
    rng = np.random.default_rng(0)
    for name in ("g.ply", "g.pcd", "g.xyz", "g.pts", "g.npy"):
        path = tmp_path / name
        path.write_bytes(rng.integers(0, 256, 5000, dtype=np.uint8).tobytes())
        with pytest.raises(ScanFileError) as info:
            load_scan(path)
        assert info.value.path == str(path)


def test_point_limit(tmp_path):
    path = tmp_path / "big.ply"
    path.write_bytes(_ascii_ply(_rows(300)))
    with pytest.raises(ScanFileError, match="300 points, more than the limit of 200"):
        load_scan(path, max_points=200)
    np.save(tmp_path / "big.npy", np.zeros((300, 3)))
    with pytest.raises(ScanFileError, match="more than the limit"):
        load_scan(tmp_path / "big.npy", max_points=200)
    (tmp_path / "big.xyz").write_text("".join(r + "\n" for r in _rows(300)))
    with pytest.raises(ScanFileError, match="more than the limit"):
        load_scans([tmp_path / "big.xyz"], max_points=200)
    assert load_scan(path, max_points=None).num_points == 300


def test_duplicate_points_only(tmp_path):
    np.save(tmp_path / "dup.npy", np.repeat(np.eye(3)[:2], 300, axis=0))
    with pytest.raises(ScanFileError, match="600 points but only 2 distinct; need min_points"):
        load_scan(tmp_path / "dup.npy")


def test_symlinks_and_undecodable_names(tmp_path):
    points, _, _ = _cloud()
    np.save(tmp_path / "a.npy", points)
    (tmp_path / "dangling.npy").symlink_to(tmp_path / "gone.npy")
    with pytest.raises(ScanFileError, match="dangling symbolic link") as info:
        list_scan_files(tmp_path)
    assert info.value.path == str(tmp_path / "dangling.npy")
    (tmp_path / "dangling.npy").unlink()
    (tmp_path / "loop.npy").symlink_to(tmp_path / "loop.npy")
    with pytest.raises(ScanFileError, match="symbolic link loop"):
        load_scans(tmp_path)
    (tmp_path / "loop.npy").unlink()
    import os

    bad = os.path.join(os.fsencode(tmp_path), b"b\xffd.npy")
    with open(bad, "wb") as f:
        np.save(f, points)
    with pytest.raises(ScanFileError, match="not valid UTF-8") as info:
        list_scan_files(tmp_path)
    assert "b\\xffd.npy" in str(info.value)
    str(info.value).encode("utf-8")  # printable


def test_unknown_files_are_listed_as_skipped(tmp_path):
    from mvreg.io.loaders import scan_folder

    points, _, _ = _cloud()
    np.save(tmp_path / "a.npy", points)
    for name in ("notes.txt", "scan.las2", "README", "ground_truth.json", "x.md", "y.conf"):
        (tmp_path / name).write_text("x")
    (tmp_path / "sub").mkdir()
    listing = scan_folder(tmp_path)
    assert [p.name for p in listing.files] == ["a.npy"]
    skipped = {d["file"]: d["reason"] for d in listing.skipped_report()}
    assert skipped == {
        "notes.txt": "unsupported file type '.txt'",
        "scan.las2": "unsupported file type '.las2'",
        "sub": "a folder",
    }


# ---------------------------------------------------------------- LAS / LAZ / E57
def _write_las(path: Path, points, colors=None) -> Path:
    import laspy

    header = laspy.LasHeader(point_format=2 if colors is not None else 0, version="1.2")
    header.offsets = np.floor(points.min(axis=0))
    header.scales = [1e-4, 1e-4, 1e-4]
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    if colors is not None:
        las.red, las.green, las.blue = (np.round(colors * 65535).astype(np.uint16)).T
    las.write(str(path))
    return path


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_and_laz_round_trip_with_georeferenced_offsets(tmp_path, suffix):
    points, _, colors = _cloud()
    points = points + [500_000.0, 4_000_000.0, 200.0]  # UTM-scale coordinates
    scan = load_scan(_write_las(tmp_path / f"scan{suffix}", points, colors))
    assert scan.num_points == 200 and scan.points.dtype == np.float64
    assert np.max(np.abs(scan.points - points)) < 1e-4
    assert np.max(np.abs(scan.colors - colors)) < 1e-4
    assert suffix in supported_suffixes()


def _write_e57(path: Path, scans: list[tuple[np.ndarray, np.ndarray | None]]) -> Path:
    import pye57
    from scipy.spatial.transform import Rotation

    e57 = pye57.E57(str(path), mode="w")
    for k, (points, pose) in enumerate(scans):
        data = {f"cartesian{c}": points[:, i] for i, c in enumerate("XYZ")}
        kwargs = {}
        if pose is not None:
            x, y, z, w = Rotation.from_matrix(pose[:3, :3]).as_quat()
            kwargs = {"rotation": np.array([w, x, y, z]), "translation": pose[:3, 3]}
        e57.write_scan_raw(data, name=f"station {k}", **kwargs)
    e57.close()
    return path


def test_e57_scans_and_their_stored_poses(tmp_path):
    from scipy.spatial.transform import Rotation

    a, _, _ = _cloud(200, seed=1)
    b, _, _ = _cloud(300, seed=2)
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec([0.1, 0.2, 0.3]).as_matrix()
    pose[:3, 3] = [1e6, 2e6, 10.0]
    path = _write_e57(tmp_path / "site.e57", [(a, pose), (b, None)])
    scans = load_scans(tmp_path)
    assert [s.name for s in scans] == ["site.e57#0", "site.e57#1"]
    assert np.allclose(scans[0].points, a) and np.allclose(scans[1].points, b)
    assert np.allclose(scans[0].T_world_scan_hint, pose, rtol=0, atol=1e-6)
    with pytest.raises(ScanFileError, match="holds 2 scans"):
        load_scan(path)
    single = load_scan(_write_e57(tmp_path / "one.e57", [(a, None)]))
    assert single.name == "one.e57" and single.num_points == 200


@pytest.mark.parametrize("suffix", [".las", ".laz", ".e57"])
def test_corrupt_las_and_e57_are_named(tmp_path, suffix):
    path = tmp_path / f"bad{suffix}"
    path.write_bytes(b"LASF" + bytes(range(256)) * 4 if suffix != ".e57" else b"ASTM-E57" * 100)
    with pytest.raises(ScanFileError) as info:
        load_scan(path)
    assert info.value.path == str(path)


def test_the_load_stage_reads_two_at_a_time_in_file_order(tmp_path):
    """The pipeline's load stage reads files on threads: the scans come in the folder's
    order, and of two bad files the first in that order is the one named."""
    from mvreg.pipeline.load import LOAD_THREADS, load_source
    from mvreg.pipeline.run import NoProgress

    assert LOAD_THREADS >= 2
    rng = np.random.default_rng(0)
    sizes = [300, 200, 400, 250, 350]
    for k, n in enumerate(sizes):
        np.save(tmp_path / f"s{k}.npy", rng.normal(size=(n, 3)))
    loaded = load_source(tmp_path, None, 100, None, None, NoProgress())
    assert [s.name for s in loaded.scans] == [f"s{k}.npy" for k in range(5)]
    assert [len(s.points) for s in loaded.scans] == sizes
    (tmp_path / "s1.npy").write_bytes(b"not numpy")
    (tmp_path / "s3.npy").write_bytes(b"")
    with pytest.raises(ScanFileError) as info:
        load_source(tmp_path, None, 100, None, None, NoProgress())
    assert info.value.path == str(tmp_path / "s1.npy")
