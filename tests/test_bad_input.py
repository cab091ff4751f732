"""Bad-input corpus (issue 16): every hostile or faulty input gets a one-line error naming
the culprit and a documented exit code, or a correct result.

Each case is generated at test time from tiny synthetic files and run in process, through
the CLI (``mvreg.cli.app`` with typer's CliRunner) or the library. Nearly all fail before
registration starts, so the whole file runs in seconds.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from mvreg.cli import app
from mvreg.errors import InputError, ProblemError, ScanFileError

runner = CliRunner()
RNG = np.random.default_rng(16)
GOOD = RNG.normal(size=(300, 3))


@dataclass
class Case:
    """``make(tmp)`` writes the input and returns the CLI arguments; the run must exit with
    ``code`` and its output contain every needle (file names, values)."""

    id: str
    make: Callable[[Path], list[str]]
    code: int
    needles: tuple[str, ...]


def run_case(case: Case, tmp: Path) -> str:
    args = case.make(tmp)
    r = runner.invoke(app, args)
    out = r.output
    assert r.exit_code == case.code, out
    assert "Traceback" not in out, out
    for needle in case.needles:
        assert needle in out, (needle, out)
    errors = [line for line in out.splitlines() if line.startswith("mvreg: error")]
    if case.code == 2 and errors:
        assert len(errors) == 1, out
    return out


# ------------------------------------------------------------------ scan folders
def scan_folder(tmp: Path, bad_name: str, content: bytes | None) -> Path:
    """Two good scans and one bad file ``bad_name`` (None: written by the caller)."""
    d = tmp / "scans"
    d.mkdir(exist_ok=True)
    np.save(d / "a.npy", GOOD)
    np.save(d / "b.npy", GOOD[::-1] + 0.01)
    if content is not None:
        (d / bad_name).write_bytes(content)
    return d


def register_args(tmp: Path, folder: Path, *extra: str) -> list[str]:
    return ["register", str(folder), "--out", str(tmp / "out"), "--no-rrd", *extra]


def ply_header(n: int, fmt: str = "ascii", props: str = "float") -> str:
    return (
        f"ply\nformat {fmt} 1.0\nelement vertex {n}\n"
        f"property {props} x\nproperty {props} y\nproperty {props} z\nend_header\n"
    )


def ascii_rows(k: int = 150) -> list[str]:
    return [f"{i * 0.01:.3f} {np.sin(i):.5f} {np.cos(i * 0.7):.5f}" for i in range(k)]


def ply_with(rows: list[str], n: int | None = None, props: str = "float") -> bytes:
    return (
        ply_header(len(rows) if n is None else n, props=props) + "\n".join(rows) + "\n"
    ).encode()


def pcd_ascii(rows: list[str], n: int | None = None) -> bytes:
    n = len(rows) if n is None else n
    head = (
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA ascii\n"
    )
    return (head + "\n".join(rows) + "\n").encode()


def _scan_case(cid: str, name: str, content: bytes, *needles: str) -> Case:
    def make(tmp: Path) -> list[str]:
        return register_args(tmp, scan_folder(tmp, name, content))

    return Case(cid, make, 2, (name, *needles))


def _bad_token_cases() -> list[Case]:
    cases = []
    tokens = ["x", "1e999", "-1e999", "1e39", "inf", "-inf", "1.2.3", "--1", "0x1g", "1,5", "é"]
    for tok in tokens:
        for where in (0, 75, 149):
            rows = ascii_rows()
            rows[where] = f"0.5 {tok} 0.25"
            line = 8 + where
            cases.append(
                _scan_case(f"ply-token-{tok}-row{where}", "bad.ply", ply_with(rows), f"line {line}")
            )
        rows = ascii_rows()
        rows[20] = f"0.5 {tok} 0.25"
        cases.append(_scan_case(f"pcd-token-{tok}", "bad.pcd", pcd_ascii(rows), "line 31"))
    for tok in ("256", "-1", "1.5"):
        rows = [f"{i % 200} {i % 100} {i % 50}" for i in range(150)]
        rows[10] = f"1 {tok} 1"
        cases.append(
            _scan_case(f"ply-uchar-{tok}", "u.ply", ply_with(rows, props="uchar"), "line 18")
        )
    return cases


def _width_and_count_cases() -> list[Case]:
    rows = ascii_rows()
    cases = [
        _scan_case("ply-short-row", "w.ply", ply_with(rows[:5] + ["1 2"] + rows[6:]), "line 13"),
        _scan_case(
            "ply-long-row", "w.ply", ply_with(rows[:5] + ["1 2 3 4"] + rows[6:]), "4 values"
        ),
        _scan_case("ply-cut-last", "w.ply", ply_with(rows[:-1] + ["1 2"]), "incomplete"),
        _scan_case("pcd-short-row", "w.pcd", pcd_ascii(rows[:5] + ["1 2"] + rows[6:]), "line 16"),
    ]
    for declared, held in ((100, 150), (149, 150), (151, 150), (1000, 150)):
        cases.append(
            _scan_case(
                f"ply-ascii-declares-{declared}-holds-{held}",
                "c.ply",
                ply_with(ascii_rows(held), n=declared),
                f"declares {declared}",
                f"holds {held}",
            )
        )
        cases.append(
            _scan_case(
                f"pcd-ascii-declares-{declared}-holds-{held}",
                "c.pcd",
                pcd_ascii(ascii_rows(held), n=declared),
                f"declares {declared}",
                f"holds {held}",
            )
        )
        body = np.asarray(RNG.normal(size=(held, 3)), "<f4").tobytes()
        cases.append(
            _scan_case(
                f"ply-binary-declares-{declared}-holds-{held}",
                "c.ply",
                ply_header(declared, "binary_little_endian").encode() + body,
                f"{declared}",
            )
        )
    return cases


def _garbage_cases() -> list[Case]:
    cases = []
    for suffix in (".ply", ".pcd", ".xyz", ".xyzn", ".xyzrgb", ".pts", ".npy"):
        junk = RNG.integers(0, 256, 4000, dtype=np.uint8).tobytes()
        cases.append(_scan_case(f"garbage{suffix}", f"junk{suffix}", junk))
        cases.append(_scan_case(f"empty{suffix}", f"empty{suffix}", b"", "empty file"))
        text = b"hello world\n" * 200
        cases.append(_scan_case(f"text{suffix}", f"text{suffix}", text))
    return cases


def _content_cases() -> list[Case]:
    dup = (ply_header(400) + "1 2 3\n4 5 6\n" * 200).encode()
    nan = ("nan nan nan\n" * 300).encode()
    return [
        _scan_case("duplicates-only", "dup.ply", dup, "400 points but only 2 distinct"),
        _scan_case("nan-only", "nan.xyz", nan, "NaN"),
        _scan_case("no-vertices", "none.ply", ply_header(0).encode(), "no vertices"),
        _scan_case("no-end-header", "h.ply", b"ply\nformat ascii 1.0\n" * 3, "corrupt header"),
        _scan_case("bad-format", "f.ply", ply_header(3, "utf8").encode(), "unknown PLY format"),
        _scan_case(
            "bad-type",
            "t.ply",
            ply_header(3, props="float128").encode() + b"1 2 3\n" * 3,
            "unknown PLY property type",
        ),
        _scan_case(
            "ply-binary-body-in-ascii",
            "long.ply",
            ply_header(300).encode() + bytes(range(1, 10)) * 300_000,
            "line 8 is longer than",
        ),
        _scan_case("pickle-npy", "p.npy", b"\x93NUMPY\x01\x00v\x00{'descr': '|O'," + b" " * 200),
    ]


def _link(kind: str) -> Callable[[Path], list[str]]:
    def make(tmp: Path) -> list[str]:
        d = scan_folder(tmp, "", None)
        if kind == "dangling":
            (d / "link.npy").symlink_to(tmp / "missing.npy")
        elif kind == "loop":
            (d / "link.npy").symlink_to(d / "link.npy")
        elif kind == "loop2":
            (d / "link.npy").symlink_to(d / "other.npy")
            (d / "other.npy").symlink_to(d / "link.npy")
        elif kind == "undecodable":
            with open(os.path.join(os.fsencode(d), b"caf\xe9.npy"), "wb") as f:
                np.save(f, GOOD)
        elif kind == "dir":
            (d / "sub.ply").mkdir()
            (d / "notes.txt").write_text("x")
            return register_args(tmp, d, "--seed", "-5")
        return register_args(tmp, d)

    return make


LINK_CASES = [
    Case("symlink-dangling", _link("dangling"), 2, ("link.npy", "dangling symbolic link")),
    Case("symlink-loop", _link("loop"), 2, ("link.npy", "symbolic link loop")),
    Case("symlink-loop-2", _link("loop2"), 2, ("symbolic link loop",)),
    Case("undecodable-name", _link("undecodable"), 2, ("caf\\xe9.npy", "not valid UTF-8")),
    Case("register-negative-seed", _link("dir"), 2, ("seed",)),
]


def _las_bytes(count: int = 300, held: int = 300, vlrs: int = 0, offset: int = 227) -> bytes:
    import struct

    head = bytearray(227)
    head[:4] = b"LASF"
    head[24:26] = bytes([1, 2])
    struct.pack_into("<HII", head, 94, 227, offset, vlrs)
    struct.pack_into("<BHI", head, 104, 0, 20, count)
    struct.pack_into("<6d", head, 131, 1e-3, 1e-3, 1e-3, 0.0, 0.0, 0.0)
    return (
        bytes(head)
        + bytes(offset - 227 if offset < 10**6 else 0)
        + RNG.integers(0, 9, 20 * held).astype(np.uint8).tobytes()
    )


def _las_cases() -> list[Case]:
    return [
        _scan_case(
            "las-truncated", "t.las", _las_bytes(300, 120), "declares 300 points", "holds 120"
        ),
        _scan_case("las-huge-count", "h.las", _las_bytes(2**32 - 1, 10), "declares 4294967295"),
        _scan_case("las-vlrs-do-not-fit", "v.las", _las_bytes(vlrs=10**8), "VLRs do not fit"),
        _scan_case("las-offset-beyond-end", "o.las", _las_bytes(offset=10**9, held=0), "corrupt"),
        _scan_case("las-short-header", "s.las", b"LASF" + bytes(100), "truncated LAS header"),
        _scan_case("las-bad-signature", "b.las", b"LASX" + bytes(400), "bad signature"),
        _scan_case("laz-garbage", "g.laz", b"LASF" + bytes(range(256)) * 4),
        _scan_case("e57-garbage", "g.e57", b"ASTM-E57" * 100),
    ]


SCAN_CASES = (
    _bad_token_cases()
    + _width_and_count_cases()
    + _garbage_cases()
    + _content_cases()
    + _las_cases()
    + LINK_CASES
)


@pytest.mark.parametrize("case", SCAN_CASES, ids=lambda c: c.id)
def test_scan_files(tmp_path, case):
    run_case(case, tmp_path)
    assert not (tmp_path / "out" / "poses.json").exists()


# ------------------------------------------------------------------ poses / ground truth
def rigid(seed: int) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    t = np.eye(4)
    t[:3, :3] = Rotation.random(random_state=seed).as_matrix()
    t[:3, 3] = np.random.default_rng(seed).normal(size=3)
    return t


def poses_file(path: Path, poses: dict, fmt: str | None = "mvreg.poses/1") -> Path:
    data = {"poses": {k: np.asarray(v).tolist() if isinstance(v, np.ndarray) else v
                      for k, v in poses.items()}}  # fmt: skip
    if fmt is not None:
        data["format"] = fmt
    path.write_text(json.dumps(data))
    return path


def _bad_poses() -> dict[str, tuple[object, str]]:
    scaled = rigid(1)
    scaled[:3, :3] *= 1.01
    reflect = rigid(2)
    reflect[:3, 0] *= -1
    row = rigid(3)
    row[3, 0] = 0.5
    nan = rigid(4)
    nan[0, 3] = np.nan
    sheared = rigid(5)
    sheared[0, 1] += 1e-3
    return {
        "3x3": (np.eye(3), "not a 4x4 matrix"),
        "3x4": (rigid(0)[:3], "not a 4x4 matrix"),
        "5x5": (np.eye(5), "not a 4x4 matrix"),
        "scaled": (scaled, "not rigid"),
        "sheared": (sheared, "not rigid"),
        "reflection": (reflect, "reflection"),
        "last-row": (row, "last row"),
        "nan": (nan, "NaN or inf"),
        "text": ("rotation", "not"),
        "ragged": ([[1, 0, 0, 0], [0, 1, 0]], "not a matrix of numbers"),
        "nested": ([[[1]]], "not a 4x4 matrix"),
        "null": (None, "not a"),
    }


BAD_POSES = _bad_poses()


def _truth_case(key: str) -> Case:
    pose, reason = BAD_POSES[key]

    def make(tmp: Path) -> list[str]:
        d = scan_folder(tmp, "", None)
        poses_file(d / "ground_truth.json", {"a.npy": rigid(9), "b.npy": pose})
        return register_args(tmp, d)

    return Case(f"truth-{key}", make, 2, ("ground_truth.json", "'b.npy'", reason))


def _eval_case(key: str) -> Case:
    pose, reason = BAD_POSES[key]

    def make(tmp: Path) -> list[str]:
        est = poses_file(tmp / "poses.json", {"a": rigid(1), "b": rigid(2)})
        truth = poses_file(tmp / "truth.json", {"a": rigid(3), "b": pose})
        return ["eval", str(est), "--truth", str(truth)]

    reason = {"3x3": "mixed sizes"}.get(key, reason.replace("not a 4x4", "not a 3x3 or 4x4"))
    return Case(f"eval-{key}", make, 2, ("truth.json", "'b'", reason))


def _eval_other(kind: str) -> Case:
    def make(tmp: Path) -> list[str]:
        est = poses_file(tmp / "poses.json", {"a": rigid(1), "b": rigid(2), "c": rigid(3)})
        truth = tmp / "truth.json"
        if kind == "disjoint":
            poses_file(truth, {"x": rigid(1), "y": rigid(2)})
        elif kind == "one-common":
            poses_file(truth, {"a": rigid(1), "y": rigid(2)})
        elif kind == "2d-vs-3d":
            poses_file(truth, {"a": np.eye(3), "b": np.eye(3)})
        elif kind == "mixed":
            poses_file(truth, {"a": np.eye(3), "b": np.eye(4)})
        elif kind == "no-format":
            poses_file(truth, {"a": rigid(1)}, fmt=None)
        elif kind == "not-json":
            truth.write_text("{nope")
        elif kind == "binary":
            truth.write_bytes(b"\xff\xfe\x00garbage")
        elif kind == "empty":
            poses_file(truth, {})
        elif kind == "list":
            truth.write_text('{"format": "mvreg.poses/1", "poses": [1, 2]}')
        elif kind == "deep":
            truth.write_text("[" * 100000 + "]" * 100000)
        elif kind == "missing":
            pass
        return ["eval", str(est), "--truth", str(truth)]

    needles = {"disjoint": "0 scan(s) in common", "one-common": "1 scan(s) in common"}
    return Case(f"eval-{kind}", make, 2, ("truth.json", needles.get(kind, "")))


EVAL_KINDS = [
    "disjoint", "one-common", "2d-vs-3d", "mixed", "no-format", "not-json", "binary", "empty",
    "list", "deep", "missing",
]  # fmt: skip
POSE_CASES = (
    [_truth_case(k) for k in BAD_POSES]
    + [_eval_case(k) for k in BAD_POSES]
    + [_eval_other(k) for k in EVAL_KINDS]
)


@pytest.mark.parametrize("case", POSE_CASES, ids=lambda c: c.id)
def test_poses(tmp_path, case):
    run_case(case, tmp_path)


def test_eval_of_good_poses_still_works(tmp_path):
    t = {n: rigid(i) for i, n in enumerate("abc")}
    est = poses_file(tmp_path / "poses.json", {n: rigid(7) @ v for n, v in t.items()})
    truth = poses_file(tmp_path / "truth.json", t)
    r = runner.invoke(app, ["eval", str(est), "--truth", str(truth)])
    assert r.exit_code == 0, r.output
    assert "rotation median 0.0000" in r.output


# ------------------------------------------------------------------ patch problems
def _problem_arrays() -> dict:
    from data_synth.problems import make_problem

    prob, _ = make_problem(4, 3, 3, 8, 0.0, 0.0, seed=0)
    return {"coords": prob.coords, "patch": prob.patch, "node": prob.node_ids[prob.node_index]}


def _problem_case(cid: str, edit, *needles: str, args: tuple = (), code: int = 2) -> Case:
    def make(tmp: Path) -> list[str]:
        arrays = _problem_arrays()
        edit(arrays)
        np.savez(tmp / "p.npz", **arrays)
        out = tmp / "r.json"
        if "--out-dir" in args:
            out.mkdir()
        return ["solve", str(tmp / "p.npz"), "--out", str(out)] + [
            a for a in args if a != "--out-dir"
        ]

    return Case(cid, make, code, needles)


def _set(key, fn):
    def edit(a):
        a[key] = fn(a[key])

    return edit


def _nothing(a):
    return None


PROBLEM_CASES = [
    _problem_case("complex-coords", _set("coords", lambda c: c + 1j), "'coords'", "complex"),
    _problem_case(
        "complex-weight",
        lambda a: a.update(weight=np.ones(len(a["patch"])) * (1 + 1j)),
        "'weight'",
        "complex",
    ),  # fmt: skip
    _problem_case("huge-coords", _set("coords", lambda c: c * 1e200), "'coords'", "1e+200"),
    _problem_case(
        "huge-one-coord",
        _set("coords", lambda c: np.where(c == c.max(), 1e40, c)),
        "'coords'",
        "rescale",
    ),  # fmt: skip
    _problem_case(
        "inf-coords",
        _set("coords", lambda c: np.where(c == c.max(), np.inf, c)),
        "'coords'",
        "NaN or inf",
    ),  # fmt: skip
    _problem_case("text-coords", _set("coords", lambda c: c.astype(str)), "'coords'", "real"),
    _problem_case(
        "patch-1e9",
        _set("patch", lambda p: np.where(p == p.max(), 10**9, p)),
        "1000000001 patches",
        "largest 'patch' index 1000000000",
    ),  # fmt: skip
    _problem_case(
        "patch-float-1e30",
        _set("patch", lambda p: np.where(p == 0, 1e30, p)),
        "'patch'",
        "too large",
    ),  # fmt: skip
    _problem_case(
        "patch-uint64-max",
        _set("patch", lambda p: p.astype(np.uint64) + np.uint64(2**64 - 8)),
        "'patch'",
        "too large",
    ),  # fmt: skip
    _problem_case("patch-negative", _set("patch", lambda p: p - 1), "'patch'", "negative"),
    _problem_case("patch-fraction", _set("patch", lambda p: p + 0.5), "'patch'", "integers"),
    _problem_case("node-negative", _set("node", lambda n: n - 10**6), "'node'", "negative"),
    _problem_case("node-2d", _set("node", lambda n: n[:, None]), "'node'", "1-D"),
    _problem_case("coords-1d", _set("coords", lambda c: c[:, 0]), "'coords'", "shape"),
    _problem_case("short-patch", _set("patch", lambda p: p[:-1]), "'patch' has"),
    _problem_case(
        "weight-negative", lambda a: a.update(weight=-np.ones(len(a["patch"]))), "'weight'", ">= 0"
    ),  # fmt: skip
    _problem_case("missing-node", lambda a: a.pop("node"), "missing array(s) node"),
    _problem_case("out-is-dir", _nothing, "r.json", "is a folder", args=("--out-dir",)),
    _problem_case("seed-negative", _nothing, "seed", args=("--seed", "-5")),
    _problem_case("node-1e18-ok", _set("node", lambda n: n * 10**15 + 10**18), code=0),
]


@pytest.mark.parametrize("case", PROBLEM_CASES, ids=lambda c: c.id)
def test_patch_problems(tmp_path, case):
    run_case(case, tmp_path)


def test_patch_index_1e9_is_refused_before_allocating(monkeypatch):
    """No array or list sized by the bogus index is built: names are never made."""
    from mvreg.solver.problem import PatchProblem

    a = _problem_arrays()
    a["patch"] = np.where(a["patch"] == a["patch"].max(), 10**12, a["patch"])
    with pytest.raises(ProblemError, match="patches"):
        PatchProblem(**a, num_patches=None)
    with pytest.raises(ProblemError, match="some patch would have no observations"):
        PatchProblem(**_problem_arrays(), num_patches=10**12)


def test_solve_not_a_file(tmp_path):
    (tmp_path / "p.npz").write_text("nope")
    r = runner.invoke(app, ["solve", str(tmp_path / "p.npz"), "--out", str(tmp_path / "r.json")])
    assert r.exit_code == 2 and "p.npz" in r.output


def test_library_errors_are_typed(tmp_path):
    from mvreg.io.loaders import load_scan
    from mvreg.io.poses import read_poses_json
    from mvreg.metrics import pose_errors

    (tmp_path / "a.ply").write_bytes(ply_with(ascii_rows(300)))
    with pytest.raises(ScanFileError, match="300 points, more than the limit of 100"):
        load_scan(tmp_path / "a.ply", max_points=100)
    poses_file(tmp_path / "p.json", {"a": np.eye(3)})
    assert read_poses_json(tmp_path / "p.json", dim=2)["a"].shape == (3, 3)
    with pytest.raises(InputError, match="not a 4x4"):
        read_poses_json(tmp_path / "p.json")
    with pytest.raises(InputError, match="differ"):
        pose_errors(np.stack([np.eye(4)] * 2), np.stack([np.eye(4)] * 3))
