"""Cases the hostile-input corpus (``scripts/bad_input_corpus.py``) found BAD or POOR,
each kept here as a regression test: exit code, culprit named, inputs untouched."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from mvreg.cli import app
from mvreg.errors import InputError, ScanFileError
from tests.conftest import small_tmpfs
from tests.test_bad_input import GOOD, ply_header, register_args

runner = CliRunner()


def good_folder(tmp: Path) -> Path:
    d = tmp / "scans"
    d.mkdir()
    np.save(d / "a.npy", GOOD)
    np.save(d / "b.npy", GOOD[::-1] + 0.01)
    return d


def digest(folder: Path) -> dict[str, str]:
    return {
        p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.iterdir() if p.is_file()
    }


def one_error_line(out: str, *needles: str) -> None:
    assert "Traceback" not in out, out
    errors = [line for line in out.splitlines() if line.startswith("mvreg: error")]
    assert len(errors) == 1, out
    for needle in needles:
        assert needle in errors[0], (needle, out)


# ---------------------------------------------------------------- --rrd onto an input
@pytest.mark.parametrize("force", [False, True])
@pytest.mark.parametrize("target", ["a.npy", "sub/new.rrd", "."])
def test_rrd_inside_the_input_is_refused_even_with_force(tmp_path, force, target):
    d = good_folder(tmp_path)
    (d / "sub").mkdir()
    before = digest(d)
    rrd = d / target
    args = ["register", str(d), "--out", str(tmp_path / "out"), "--rrd", str(rrd)]
    r = runner.invoke(app, args + ["--force"] * force)
    assert r.exit_code == 2, r.output
    one_error_line(r.output, "--rrd")
    assert digest(d) == before
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------- misread binary bodies
def _binary_ply(body: bytes, n: int, fmt: str) -> bytes:
    return ply_header(n, fmt, "double").encode() + body


@pytest.mark.parametrize("kind", ["random-body", "swapped-endianness"])
def test_a_misread_binary_body_is_refused_naming_the_file(tmp_path, kind):
    d = good_folder(tmp_path)
    pts = GOOD * 0.1 + [0.3, -0.2, 1.5]
    if kind == "random-body":
        body = np.random.default_rng(3).bytes(pts.size * 8)
        data = _binary_ply(body, len(pts), "binary_little_endian")
    else:  # little-endian doubles declared big-endian
        data = _binary_ply(pts.astype("<f8").tobytes(), len(pts), "binary_big_endian")
    (d / "bad.ply").write_bytes(data)
    r = runner.invoke(app, register_args(tmp_path, d))
    assert r.exit_code == 2, r.output
    one_error_line(r.output, "bad.ply", "not a sampled surface")
    assert "RuntimeWarning" not in r.output


def test_spacing_check_keeps_real_scales(tmp_path):
    """A surface in micrometres or at 1e6 (georeferenced) passes; the rule is a ratio."""
    from mvreg.io.loaders import Scan
    from mvreg.pipeline.load import check_spacing

    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(size=(5000, 2)), np.zeros(5000)]
    for scale, offset in ((1e-6, 0.0), (1.0, 5e6), (1e3, 0.0)):
        s = Scan(name="s", path=Path("s.ply"), points=plane * scale + offset)
        assert check_spacing(s) is s
    # what misread bytes look like: magnitudes spread over orders of magnitude
    for decades in (300, 30):
        wild = rng.choice([-1, 1], (5000, 3)) * 10 ** rng.uniform(-decades, decades, (5000, 3))
        with pytest.raises(ScanFileError, match="not a sampled surface"):
            check_spacing(Scan(name="s", path=Path("s.ply"), points=wild))


# ---------------------------------------------------------------- absurd problem sizes
def test_make_problem_too_large_is_refused_before_allocating(tmp_path):
    from data_synth.problems import make_problem

    out = tmp_path / "p.npz"
    r = runner.invoke(app, ["make-problem", "--patches", str(10**12), "--out", str(out)])
    assert r.exit_code == 2, r.output
    one_error_line(r.output, "--patches 1000000000000", "GiB")
    assert not out.exists()
    with pytest.raises(InputError, match="--patches"):
        make_problem(10**9, nodes_per_pair=20)


# ---------------------------------------------------------------- headers and text files
def _rows(k: int = 300, cols: int = 3) -> list[str]:
    return [" ".join(f"{v:.5f}" for v in GOOD[i % len(GOOD), :cols]) for i in range(k)]


def _ply(props: str, rows: list[str], version: str = "1.0") -> bytes:
    head = f"ply\nformat ascii {version}\nelement vertex {len(rows)}\n{props}end_header\n"
    return (head + "\n".join(rows) + "\n").encode()


XYZ3 = "property float x\nproperty float y\nproperty float z\n"
FILE_CASES = {
    "ply-missing-z": (
        "m.ply",
        _ply("property float x\nproperty float y\n", _rows(cols=2)),
        "no z property",
    ),
    "ply-duplicate-x": (
        "d.ply",
        _ply("property float x\nproperty float x\nproperty float z\n", _rows()),
        "'x' of vertex declared twice",
    ),
    "ply-version-2": ("v.ply", _ply(XYZ3, _rows(), "2.0"), "unsupported PLY version '2.0'"),
    "xyz-1e999": ("t.xyz", ("\n".join(_rows()[:9] + ["1 1e999 2"]) + "\n").encode(), "line 10"),
    "xyz-inf": ("t.xyz", ("\n".join(["inf 0 0"] + _rows())).encode(), "line 1: value 'inf'"),
    "xyz-comma": ("t.xyz", b"1,2,3\n" * 300, "line 1"),
    "xyz-header-line": (
        "t.xyz",
        ("x y z\n" + "\n".join(_rows())).encode(),
        "line 1: value 'x' is not a number",
    ),
    "xyz-ragged": ("t.xyz", ("\n".join(_rows()[:20] + ["1 2"] + _rows())).encode(), "line 21"),
    "xyzn-three-columns": ("t.xyzn", ("\n".join(_rows())).encode(), "at least 6"),
    "pts-count-too-high": ("t.pts", ("500\n" + "\n".join(_rows())).encode(), "declares 500"),
    "pts-count-too-low": ("t.pts", ("10\n" + "\n".join(_rows())).encode(), "holds 300"),
    "pts-no-count": ("t.pts", ("\n".join(_rows())).encode(), "not a number of points"),
    "npy-text": ("t.npy", ("\n".join(_rows())).encode(), "not a .npy file"),
}


@pytest.mark.parametrize("cid", sorted(FILE_CASES))
def test_misdeclared_files_are_refused_naming_file_and_reason(tmp_path, cid):
    name, data, needle = FILE_CASES[cid]
    d = good_folder(tmp_path)
    (d / name).write_bytes(data)
    r = runner.invoke(app, register_args(tmp_path, d))
    assert r.exit_code == 2, r.output
    one_error_line(r.output, name, needle)


def test_complex_npy_is_named_as_complex(tmp_path):
    d = good_folder(tmp_path)
    np.save(d / "c.npy", GOOD.astype(complex))
    r = runner.invoke(app, register_args(tmp_path, d))
    assert r.exit_code == 2, r.output
    one_error_line(r.output, "c.npy", "complex numbers")


@pytest.mark.parametrize("suffix", [".xyz", ".pts"])
def test_valid_text_scans_with_nan_rows_still_load(tmp_path, suffix):
    """NaN rows are dropped and counted (organised scans mark missing returns so)."""
    from mvreg.io.loaders import load_scan

    rows = _rows(cols=3)
    rows[5] = "nan nan nan"
    text = "\n".join(rows) + "\n"
    path = tmp_path / f"s{suffix}"
    path.write_text(f"{len(rows)}\n{text}" if suffix == ".pts" else text)
    scan = load_scan(path)
    assert scan.num_points == 299 and scan.num_dropped_nonfinite == 1
    assert np.allclose(scan.points[0], GOOD[0], atol=1e-5)


# ---------------------------------------------------------------- outputs
def test_a_recording_cut_short_by_a_full_disk_is_an_error_naming_it(tmp_path, monkeypatch):
    """rerun's file sink only logs a failed write; the recorder checks the file system."""
    import os

    from mvreg.io.atomic import OutputWriteError
    from mvreg.viz import make_recorder

    rrd = tmp_path / "rec.rrd"
    rec = make_recorder(rrd)
    real = os.statvfs

    class Full:
        def __init__(self, st):
            self.f_frsize, self.f_blocks, self.f_bavail = st.f_frsize, st.f_blocks, 0

    monkeypatch.setattr(os, "statvfs", lambda p: Full(real(p)))
    with pytest.raises(OutputWriteError, match="rec.rrd: cannot write"):
        rec.close()
    assert not rrd.exists() and list(tmp_path.iterdir()) == []


def test_real_full_disk_while_recording(tmp_path):
    """A tmpfs that holds poses and report but not the recording: exit 4 naming it."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()
    with small_tmpfs(mnt, "24k"):
        d = good_folder(tmp_path)
        r = runner.invoke(app, ["register", str(d), "--out", str(mnt / "o")])
        assert r.exit_code == 4, r.output
        one_error_line(r.output, "cannot write", "No space left on device")
        assert "ERROR" not in r.output
        assert [p.name for p in mnt.iterdir()] == []


def test_out_under_a_file_names_out_not_the_staging_folder(tmp_path):
    d = good_folder(tmp_path)
    (tmp_path / "afile").write_text("x")
    out = tmp_path / "afile" / "out"
    r = runner.invoke(app, ["register", str(d), "--out", str(out), "--no-rrd"])
    assert r.exit_code in (2, 4), r.output
    one_error_line(r.output, str(out))
    assert "mvreg-tmp" not in r.output


def test_dangling_ground_truth_link_is_named(tmp_path):
    d = good_folder(tmp_path)
    (d / "ground_truth.json").symlink_to(tmp_path / "nowhere.json")
    r = runner.invoke(app, register_args(tmp_path, d))
    assert r.exit_code == 2, r.output
    one_error_line(r.output, "ground_truth.json", "dangling symbolic link")


def test_ground_truth_of_another_format_says_which(tmp_path):
    d = good_folder(tmp_path)
    (d / "ground_truth.json").write_text('{"format": "mvreg.poses/9", "poses": {}}')
    r = runner.invoke(app, register_args(tmp_path, d))
    assert r.exit_code == 2, r.output
    one_error_line(r.output, "ground_truth.json", "'mvreg.poses/9'")


# ---------------------------------------------------------------- sequences
def test_sequence_warnings_reach_the_terminal(tmp_path):
    """A timestamps.txt that does not fit the frames is named on stderr, not only in the
    report; mvreg synth's own ground_truth_tum.txt is a known sidecar (no warning)."""
    seq = tmp_path / "seq"
    r = runner.invoke(
        app,
        ["synth", "builtin", "--out", str(seq), "--sequence", "--views", "12",
         "--points-per-scan", "2000", "--seed", "1"],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    (seq / "timestamps.txt").write_text("0.0\n0.1\n0.2\n")
    r = runner.invoke(app, register_args(tmp_path, seq, "--sequence"))
    assert r.exit_code in (0, 3), r.output
    warnings = [ln for ln in r.output.splitlines() if ln.startswith("mvreg: warning")]
    assert any("timestamps.txt" in w and "12 scans" in w for w in warnings), r.output
    assert not any("ground_truth_tum.txt" in w for w in warnings), r.output


# ---------------------------------------------------------------- options
def test_voxel_larger_than_the_scans_names_the_option(tmp_path):
    d = good_folder(tmp_path)
    r = runner.invoke(app, register_args(tmp_path, d, "--voxel-size", "1e9"))
    assert r.exit_code == 2, r.output
    one_error_line(r.output, "voxel_size 1e+09 is too large", "use at most")


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_with_a_header_line_too_long_for_open3d_is_read_by_numpy(tmp_path, fmt):
    """RPly (Open3D) aborts the process on a ~1 KB header line; NumPy reads those files."""
    from mvreg.io.loaders import load_scan

    pts = GOOD[:200] + [1.0, 2.0, 3.0]
    rgb = (np.arange(600).reshape(200, 3) % 256).astype(np.uint8)
    head = (
        f"ply\nformat {fmt} 1.0\ncomment {'c' * 5000}\nelement vertex 200\n"
        "property double x\nproperty double y\nproperty double z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    ).encode()
    if fmt == "ascii":
        rows = zip(pts, rgb, strict=True)
        body = "".join(f"{x:.17g} {y:.17g} {z:.17g} {r} {g} {b}\n" for (x, y, z), (r, g, b) in rows)
        body = body.encode()
    else:
        o = "<" if fmt == "binary_little_endian" else ">"
        rows = np.empty(200, [("p", f"{o}f8", 3), ("c", "u1", 3)])
        rows["p"], rows["c"] = pts, rgb
        body = rows.tobytes()
    (tmp_path / "long.ply").write_bytes(head + body)
    scan = load_scan(tmp_path / "long.ply")
    assert np.array_equal(scan.points, pts)
    assert np.allclose(scan.colors, rgb / 255.0)


def _cli_cases(tmp: Path) -> dict[str, tuple[list[str], tuple[str, ...]]]:
    d = good_folder(tmp)
    (tmp / "bad.yaml").write_text("a: [1, 2\nb: {\n")
    out = ["--out", str(tmp / "out"), "--no-rrd"]
    p = tmp / "p.npz"
    runner.invoke(app, ["make-problem", "--patches", "10", "--degree", "3", "--out", str(p)])
    return {
        "refine-1e6": (["register", str(d), *out, "--refine", "1000000"], ("refine.rounds",)),
        "ransac-1e12": (
            ["register", str(d), *out, "--set", "align.ransac_max_iterations=1000000000000"],
            ("align.ransac_max_iterations",),
        ),
        "threads-1e5": (["register", str(d), *out, "--threads", "100000"], ("threads",)),
        "config-yaml-broken": (
            ["register", str(d), *out, "--config", str(tmp / "bad.yaml")],
            ("bad.yaml", "not valid YAML (line 2"),
        ),
        "synth-distance-1e12": (
            ["synth", "builtin", "--out", str(tmp / "s"), "--distance", "1e12"],
            ("distance must be in (0.5, 1000]",),
        ),
        "synth-elevation-nan": (
            ["synth", "builtin", "--out", str(tmp / "s"), "--elevation", "nan"],
            ("elevation must be in [-90, 90]",),
        ),
        "make-problem-degree-1e9": (
            ["make-problem", "--degree", "1000000000", "--out", str(tmp / "q.npz")],
            ("--degree 1000000000", "99 others"),
        ),
        "make-problem-nodes-1e9": (
            ["make-problem", "--nodes-per-pair", "1000000000", "--out", str(tmp / "q.npz")],
            ("--nodes-per-pair 1000000000", "GiB"),
        ),
        "rrd-is-a-result-file": (
            ["register", str(d), "--out", str(tmp / "out"), "--rrd", str(tmp / "out/poses.json")],
            ("--rrd", "poses.json"),
        ),
        "solve-out-is-input": (
            ["solve", str(p), "--out", str(p), "--force"],
            ("--out", "is the input"),
        ),
    }


CLI_CASE_IDS = [
    "refine-1e6", "ransac-1e12", "threads-1e5", "config-yaml-broken", "synth-distance-1e12",
    "synth-elevation-nan", "make-problem-degree-1e9", "make-problem-nodes-1e9",
    "rrd-is-a-result-file", "solve-out-is-input",
]  # fmt: skip


@pytest.mark.parametrize("cid", CLI_CASE_IDS)
def test_absurd_options_are_refused_up_front_naming_them(tmp_path, cid):
    args, needles = _cli_cases(tmp_path)[cid]
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    r = runner.invoke(app, args)
    assert r.exit_code == 2, r.output
    one_error_line(r.output, *needles)
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before
    assert not (tmp_path / "out").exists() and not (tmp_path / "s").exists()


def test_make_problem_negative_seed_is_a_usage_error(tmp_path):
    r = runner.invoke(app, ["make-problem", "--seed", "-1", "--out", str(tmp_path / "p.npz")])
    assert r.exit_code == 2 and "Traceback" not in r.output, r.output
    assert not (tmp_path / "p.npz").exists()


def test_merged_laz_of_a_previous_run_is_mvregs_own(tmp_path):
    from mvreg.io.output_folder import OutputFolder

    out = tmp_path / "out"
    out.mkdir()
    (out / "poses.json").write_text("{}")
    (out / "merged.laz").write_bytes(b"old")
    OutputFolder(out, force=True).check()  # no "files mvreg did not write"


@pytest.mark.parametrize(
    "args, needle",
    [
        (["register", "{d}", "--out", "{o}", "--voxel-size", "abc"], "'--voxel-size'"),
        (["register", "{d}", "--out", "{o}", "--nosuch"], "--nosuch"),
        (["make-problem", "--out", "{o}", "--patches", "1"], "'--patches'"),
        (["nosuchcommand"], "nosuchcommand"),
    ],
)
def test_usage_errors_are_one_line_from_the_real_cli(tmp_path, args, needle):
    """click's usage errors (typer prints them as a boxed panel) are one line, exit 2."""
    import subprocess
    import sys

    d = good_folder(tmp_path)
    argv = [a.format(d=d, o=tmp_path / "out") for a in args]
    r = subprocess.run(
        [sys.executable, "-m", "mvreg.cli", *argv], capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("mvreg: error: "), r.stderr
    assert needle in lines[0]
    assert not (tmp_path / "out").exists()


def test_points_dropped_from_a_scan_are_named_in_a_warning(tmp_path):
    d = good_folder(tmp_path)
    bad = GOOD.copy()
    bad[7] = np.nan
    bad[9, 1] = np.inf
    np.save(d / "c.npy", bad)
    r = runner.invoke(app, register_args(tmp_path, d))
    assert r.exit_code in (0, 3), r.output
    warnings = [ln for ln in r.output.splitlines() if ln.startswith("mvreg: warning")]
    assert any("c.npy: 2 points with a NaN or infinite coordinate" in w for w in warnings)


def _pcd(data: str, size: int, body: bytes, fields: str = "x y z", n: int = 300) -> bytes:
    k = len(fields.split())
    head = (
        f"VERSION 0.7\nFIELDS {fields}\nSIZE {' '.join([str(size)] * k)}\n"
        f"TYPE {' '.join(['F'] * k)}\nCOUNT {' '.join(['1'] * k)}\nWIDTH {n}\nHEIGHT 1\n"
        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n"
    )
    return head.encode() + body


def test_binary_pcd_with_double_coordinates_is_read_not_zeroed(tmp_path):
    """Open3D reads 8-byte PCD coordinates as zeros ("only 1 distinct point")."""
    from mvreg.io.loaders import load_scan

    nrm = GOOD / np.linalg.norm(GOOD, axis=1, keepdims=True)
    body = np.hstack([GOOD, nrm]).astype("<f8").tobytes()
    fields = "x y z normal_x normal_y normal_z"
    (tmp_path / "d.pcd").write_bytes(_pcd("binary", 8, body, fields))
    scan = load_scan(tmp_path / "d.pcd")
    assert np.array_equal(scan.points, GOOD) and np.allclose(scan.normals, nrm)
    (tmp_path / "c.pcd").write_bytes(_pcd("binary_compressed", 8, b"\0" * 64))
    with pytest.raises(ScanFileError, match="corrupt binary_compressed PCD"):
        load_scan(tmp_path / "c.pcd")


def _literal_lzf(raw: bytes) -> bytes:
    """Valid LZF made of literal runs only (32 bytes at most each)."""
    return b"".join(
        bytes([len(raw[k : k + 32]) - 1]) + raw[k : k + 32] for k in range(0, len(raw), 32)
    )


def test_binary_compressed_pcd_with_double_coordinates_is_decompressed(tmp_path):
    from mvreg.io.loaders import load_scan

    raw = np.ascontiguousarray(GOOD.T).astype("<f8").tobytes()  # field after field
    packed = _literal_lzf(raw)
    body = np.array([len(packed), len(raw)], "<u4").tobytes() + packed
    (tmp_path / "c.pcd").write_bytes(_pcd("binary_compressed", 8, body))
    assert np.array_equal(load_scan(tmp_path / "c.pcd").points, GOOD)


def test_lzf_decoder_reads_open3d_compressed_pcd(tmp_path):
    """Open3D's own binary_compressed (float32) output, decoded by mvreg's LZF reader."""
    import open3d as o3d

    from mvreg.io.loaders.lzf import lzf_decompress

    pts = np.repeat(GOOD[:50], 4, axis=0)  # repeats: back references
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    o3d.io.write_point_cloud(str(tmp_path / "o.pcd"), pcd, compressed=True)
    data = (tmp_path / "o.pcd").read_bytes()
    body = data[data.index(b"DATA binary_compressed\n") + 23 :]
    size, raw_size = np.frombuffer(body[:8], "<u4")
    raw = lzf_decompress(body[8 : 8 + size], int(raw_size))
    got = np.frombuffer(raw, "<f4").reshape(3, -1).T
    assert size < raw_size and np.allclose(got, pts, atol=1e-6)


def test_ply_properties_in_any_order_are_read_by_name(tmp_path):
    """Open3D returns garbage for a vertex element declared z, y, x."""
    from mvreg.io.loaders import load_scan

    head = ply_header(len(GOOD), "binary_little_endian", "double").replace(
        "property double x\nproperty double y\nproperty double z",
        "property double z\nproperty double y\nproperty double x",
    )
    (tmp_path / "zyx.ply").write_bytes(head.encode() + GOOD[:, ::-1].astype("<f8").tobytes())
    assert np.array_equal(load_scan(tmp_path / "zyx.ply").points, GOOD)


def test_ground_truth_of_scans_not_in_the_folder_is_named(tmp_path):
    from mvreg.io.poses import write_poses_json

    d = good_folder(tmp_path)
    write_poses_json(d / "ground_truth.json", {n: np.eye(4) for n in ("a.npy", "scan_999.ply")})
    r = runner.invoke(app, register_args(tmp_path, d))
    assert r.exit_code in (0, 3), r.output
    warnings = [ln for ln in r.output.splitlines() if ln.startswith("mvreg: warning")]
    assert any("ground truth" in w and "scan_999.ply" in w for w in warnings), r.output
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["ground_truth_without_scan"] == ["scan_999.ply"]


@pytest.mark.parametrize("policy", ["balanced", "theorem4"])
def test_solve_rho_policy_names_from_the_help_work(tmp_path, policy):
    p, out = tmp_path / "p.npz", tmp_path / "r.json"
    runner.invoke(app, ["make-problem", "--patches", "12", "--degree", "4", "--out", str(p)])
    r = runner.invoke(app, ["solve", str(p), "--out", str(out), "--rho", policy])
    assert r.exit_code == 0, r.output
    assert f'"rho_policy": "{policy}"' in out.read_text()


def test_eval_names_truth_scans_without_a_pose_in_one_warning_line(tmp_path):
    from mvreg.io.poses import write_poses_json

    res = tmp_path / "res"
    res.mkdir()
    write_poses_json(res / "poses.json", {"a": np.eye(4), "b": np.eye(4)})
    names = ["a", "b", *(f"s{k}" for k in range(1000))]
    write_poses_json(tmp_path / "gt.json", {n: np.eye(4) for n in names})
    r = runner.invoke(app, ["eval", str(res), "--truth", str(tmp_path / "gt.json")])
    assert r.exit_code == 0, r.output
    warnings = [ln for ln in r.output.splitlines() if "have no pose" in ln]
    assert len(warnings) == 1 and warnings[0].startswith("mvreg: warning: ")
    assert "1000 scan(s)" in warnings[0] and len(warnings[0]) < 300


def test_pts_rows_of_seven_values_are_read_as_xyz_intensity_rgb(tmp_path):
    """Open3D misreads them (2102 points but only 78 distinct, in the corpus)."""
    from mvreg.io.loaders import load_scan

    rgb = np.arange(len(GOOD) * 3).reshape(-1, 3) % 256
    rows = [f"{x:.9f} {y:.9f} {z:.9f} 7 {r} {g} {b}" for (x, y, z), (r, g, b) in
            zip(GOOD, rgb, strict=True)]  # fmt: skip
    (tmp_path / "s.pts").write_text(f"{len(rows)}\n" + "\n".join(rows) + "\n")
    scan = load_scan(tmp_path / "s.pts")
    assert np.allclose(scan.points, GOOD, atol=1e-8) and np.allclose(scan.colors, rgb / 255)


def test_a_recording_whose_writer_died_is_an_error_naming_it(tmp_path, monkeypatch):
    """rerun raises a bare RuntimeError ('File-writer thread shut down prematurely')."""
    from mvreg.io.atomic import OutputWriteError
    from mvreg.viz import make_recorder

    rec = make_recorder(tmp_path / "rec.rrd")

    def died(*a, **k):
        raise RuntimeError("File-writer thread shut down prematurely")

    monkeypatch.setattr(rec._rec, "flush", died)
    with pytest.raises(OutputWriteError, match="rec.rrd: cannot write"):
        rec.close()
    assert list(tmp_path.iterdir()) == []


def test_a_huge_iteration_cap_is_a_cap_not_an_error(tmp_path):
    p, out = tmp_path / "p.npz", tmp_path / "r.json"
    runner.invoke(app, ["make-problem", "--patches", "12", "--degree", "4", "--out", str(p)])
    r = runner.invoke(app, ["solve", str(p), "--out", str(out), "--max-iter", "1000000000"])
    assert r.exit_code == 0, r.output


def test_make_problem_default_degree_fits_few_patches(tmp_path):
    """The default degree adapts to M (5 patches: every pair); a given one is checked."""
    r = runner.invoke(app, ["make-problem", "--patches", "5", "--out", str(tmp_path / "p.npz")])
    assert r.exit_code == 0, r.output
