"""Hostile-input corpus, family 1: scan files (PLY, PCD, XYZ/PTS, NPY, E57, LAS/LAZ, file
system oddities). The base is 8 synthetic scans (builtin object, random frames, ~3000
points each) that register fully; most cases replace ``scan_003`` by a hostile file."""

from __future__ import annotations

import numpy as np

from bench.bad_input import (
    Case,
    Ctx,
    fmt_rows,
    lzf_literal,
    pcd_bytes,
    pcd_header,
    ply_ascii,
    ply_binary,
    ply_header,
)

REG = ["register", "{inp}", "--out", "{out}"]
CASES: list[Case] = []


def add(*a, **k) -> None:
    CASES.append(Case(*a, **k))


def bad_scan(
    cid,
    desc,
    name,
    make,
    expect=frozenset({2}),
    result="any",
    warn=None,
    note="",
    keep_truth=False,
    culprit=None,
    family="scan-files",
):
    """scan_003 replaced by ``name`` with content make(ctx) (bytes)."""

    def setup(ctx: Ctx, name=name, make=make):
        ctx.scans()
        ctx.replace(3, name, make(ctx), keep_truth=keep_truth)

    add(
        cid,
        family,
        desc,
        setup,
        REG,
        set(expect),
        culprit=[name] if culprit is None else culprit,
        expect_result=result,
        expect_warn=warn or [],
        note=note,
    )


def good_scan(cid, desc, name, make, note="", expect=frozenset({0}), warn=None):
    """A valid variant of scan_003: must register fully with correct poses."""
    bad_scan(
        cid,
        desc,
        name,
        make,
        expect=expect,
        result="full",
        keep_truth=True,
        note=note,
        culprit=[],
        warn=warn,
    )


P = 3  # the scan that is mutated


def pts(ctx):
    return ctx.pts(P)


# ---------------------------------------------------------------- PLY, valid variants
good_scan("ply-ascii", "PLY ascii", "scan_003.ply", lambda c: ply_ascii(pts(c)))
good_scan(
    "ply-ascii-crlf",
    "PLY ascii with CRLF line ends",
    "scan_003.ply",
    lambda c: ply_ascii(pts(c), nl="\r\n"),
    note="CRLF PLY files are common (Windows)",
)
good_scan(
    "ply-binary-be", "PLY binary big endian", "scan_003.ply", lambda c: ply_binary(pts(c), ">")
)
good_scan(
    "ply-binary-f32",
    "PLY binary float32",
    "scan_003.ply",
    lambda c: ply_binary(pts(c), "<", "float"),
)
good_scan(
    "ply-binary-be-f32",
    "PLY binary big endian float32",
    "scan_003.ply",
    lambda c: ply_binary(pts(c), ">", "float"),
)


def _ply_struct(ctx, props, cols, fmt="binary_little_endian", extra="", tail=b""):
    p = pts(ctx)
    n = len(p)
    dt = np.dtype([(nm, t) for nm, t in cols])
    a = np.zeros(n, dtype=dt)
    for nm, _ in cols:
        if nm in "xyz":
            a[nm] = p[:, "xyz".index(nm)]
        elif nm.startswith("n"):
            a[nm] = 0.577
        else:
            a[nm] = 200
    if fmt == "ascii":
        body = "".join(" ".join(str(v) for v in row) + "\n" for row in a.tolist()).encode()
    else:
        body = a.tobytes()
    return ply_header(n, fmt, props, extra) + body + tail


COLS_RGB = [
    ("x", "<f8"),
    ("y", "<f8"),
    ("z", "<f8"),
    ("red", "u1"),
    ("green", "u1"),
    ("blue", "u1"),
]
PROPS_RGB = [
    ("double", "x"),
    ("double", "y"),
    ("double", "z"),
    ("uchar", "red"),
    ("uchar", "green"),
    ("uchar", "blue"),
]
good_scan(
    "ply-colors",
    "PLY with uchar colors",
    "scan_003.ply",
    lambda c: _ply_struct(c, PROPS_RGB, COLS_RGB),
)
COLS_N = [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
PROPS_N = [
    ("double", "x"),
    ("double", "y"),
    ("double", "z"),
    ("float", "nx"),
    ("float", "ny"),
    ("float", "nz"),
]
good_scan(
    "ply-normals",
    "PLY with (constant, wrong) normals",
    "scan_003.ply",
    lambda c: _ply_struct(c, PROPS_N, COLS_N),
    note="normals in the file may be used to orient; wrong ones must not break the pose",
)
good_scan(
    "ply-colors-ascii",
    "PLY ascii with colors",
    "scan_003.ply",
    lambda c: _ply_struct(c, PROPS_RGB, COLS_RGB, fmt="ascii"),
)
good_scan(
    "ply-prop-before-xyz",
    "PLY with an intensity property before x y z",
    "scan_003.ply",
    lambda c: _ply_struct(
        c,
        [("float", "intensity"), ("double", "x"), ("double", "y"), ("double", "z")],
        [("intensity", "<f4"), ("x", "<f8"), ("y", "<f8"), ("z", "<f8")],
    ),
)
good_scan(
    "ply-zyx-order",
    "PLY with properties declared z y x (must be read by name)",
    "scan_003.ply",
    lambda c: _ply_struct(
        c,
        [("double", "z"), ("double", "y"), ("double", "x")],
        [("z", "<f8"), ("y", "<f8"), ("x", "<f8")],
    ),
)


def _faces(ctx):
    p = pts(ctx)
    n = len(p)
    head = ply_header(
        n, "binary_little_endian", extra="element face 2\nproperty list uchar int vertex_indices"
    )
    faces = (
        np.array([3, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0], dtype="u1")[:1].tobytes()
        + np.array([0, 1, 2], "<i4").tobytes()
    )
    return head + p.astype("<f8").tobytes() + faces + faces


good_scan("ply-faces", "PLY with an extra face element (a mesh)", "scan_003.ply", _faces)


def _vertex_list(ctx):
    p = pts(ctx)
    head = ply_header(
        len(p),
        "ascii",
        [("double", "x"), ("double", "y"), ("double", "z")],
        extra="property list uchar float extra",
    )
    body = "".join(f"{a!r} {b!r} {c!r} 2 0.5 0.25\n" for a, b, c in p)
    return head + body.encode()


bad_scan(
    "ply-vertex-list",
    "PLY ascii, vertex element with a list property",
    "scan_003.ply",
    _vertex_list,
    expect={0, 2},
    result="full",
    keep_truth=True,
    note="valid PLY; reading it or refusing it by name are both acceptable",
)
good_scan(
    "ply-comments",
    "PLY with comment and obj_info lines, extra header spaces",
    "scan_003.ply",
    lambda c: ply_binary(pts(c)).replace(
        b"comment bad_input corpus\n", b"comment a\nobj_info scanner 7\ncomment   b   c\n"
    ),
)
good_scan(
    "ply-long-comment",
    "PLY with a 1 MB comment line",
    "scan_003.ply",
    lambda c: ply_binary(pts(c)).replace(
        b"comment bad_input corpus", b"comment " + b"x" * 1_000_000
    ),
)

# ---------------------------------------------------------------- PLY, broken
B = "scan_003.ply"
bad_scan(
    "ply-swapped-endian",
    "binary_little_endian header, big-endian body",
    B,
    lambda c: ply_binary(pts(c), ">").replace(b"binary_big_endian", b"binary_little_endian"),
    expect={2, 3},
    note="values are garbage (denormals/huge): refused (2) or left out named (3)",
)
bad_scan(
    "ply-random-body",
    "valid header, random bytes body",
    B,
    lambda c: ply_header(3000) + np.random.default_rng(0).bytes(3000 * 24),
    expect={2, 3},
    note="random doubles include NaN/inf/1e300: refused or left out, named",
)


def _recount(writer, delta: int):
    """The scan written by ``writer`` with its header's vertex count off by ``delta``."""

    def make(c):
        n = len(pts(c))
        return writer(pts(c)).replace(
            f"element vertex {n}".encode(), f"element vertex {n + delta}".encode()
        )

    return make


for _cid, _desc, _writer, _delta in (
    ("ply-count-fewer", "header: fewer vertices than the body holds", ply_binary, -100),
    ("ply-count-more", "header: more vertices than the body holds", ply_binary, 100),
    ("ply-ascii-count-fewer", "ascii: fewer vertices declared than rows", ply_ascii, -5),
    ("ply-ascii-count-more", "ascii: more vertices declared than rows", ply_ascii, 5),
):
    bad_scan(_cid, _desc, B, _recount(_writer, _delta))
bad_scan(
    "ply-missing-z",
    "no z property",
    B,
    lambda c: (
        ply_header(len(pts(c)), props=[("double", "x"), ("double", "y")])
        + pts(c)[:, :2].astype("<f8").tobytes()
    ),
)
bad_scan(
    "ply-dup-x",
    "duplicate property: x x z",
    B,
    lambda c: (
        ply_header(len(pts(c)), props=[("double", "x"), ("double", "x"), ("double", "z")])
        + pts(c).astype("<f8").tobytes()
    ),
)
bad_scan(
    "ply-int-xyz",
    "int32 x y z (whole numbers: a unitless scan rounded to 1)",
    B,
    lambda c: (
        ply_header(len(pts(c)), props=[("int", "x"), ("int", "y"), ("int", "z")])
        + np.round(pts(c)).astype("<i4").tobytes()
    ),
    expect={2, 3},
    note="valid file, but rounding to whole units collapses the scan to a few points",
)
bad_scan(
    "ply-uchar-xyz",
    "uchar x y z (non-float types)",
    B,
    lambda c: (
        ply_header(len(pts(c)), props=[("uchar", "x"), ("uchar", "y"), ("uchar", "z")])
        + (np.abs(pts(c)) * 100 % 256).astype("u1").tobytes()
    ),
    expect={2, 3},
    note="valid PLY types, garbage geometry: refused or left out, named",
)
bad_scan(
    "ply-version-2",
    "format binary_little_endian 2.0",
    B,
    lambda c: ply_binary(pts(c)).replace(b"binary_little_endian 1.0", b"binary_little_endian 2.0"),
    expect={2, 0},
    result="full",
    keep_truth=True,
    note="unknown PLY version: refusing by name is the safe answer; reading it is tolerable",
)
bad_scan(
    "ply-unknown-format",
    "format binary_middle_endian 1.0",
    B,
    lambda c: ply_binary(pts(c)).replace(b"binary_little_endian", b"binary_middle_endian"),
)
bad_scan(
    "ply-no-end-header",
    "no end_header line",
    B,
    lambda c: ply_binary(pts(c)).replace(b"end_header\n", b""),
)
bad_scan(
    "ply-truncated-binary",
    "binary body cut mid-vertex",
    B,
    lambda c: ply_binary(pts(c))[: -1000 - 7],
)
bad_scan("ply-truncated-ascii", "ascii body cut mid-line", B, lambda c: ply_ascii(pts(c))[:-37])
bad_scan("ply-header-only", "header only, body missing", B, lambda c: ply_header(len(pts(c))))
bad_scan(
    "ply-bad-magic",
    "first line 'PLY ' instead of 'ply'",
    B,
    lambda c: b"PLY " + ply_binary(pts(c))[3:],
)
bad_scan("ply-no-magic", "header without the 'ply' line", B, lambda c: ply_binary(pts(c))[4:])
bad_scan(
    "ply-count-negative",
    "element vertex -5",
    B,
    lambda c: ply_header(0).replace(b"element vertex 0", b"element vertex -5"),
)
bad_scan(
    "ply-count-word",
    "element vertex many",
    B,
    lambda c: ply_header(0).replace(b"element vertex 0", b"element vertex many"),
)
bad_scan(
    "ply-count-huge",
    "element vertex 10^15 (quick refusal, no allocation)",
    B,
    lambda c: ply_header(10**15) + pts(c).astype("<f8").tobytes(),
)
bad_scan(
    "ply-vertex-twice",
    "element vertex declared twice",
    B,
    lambda c: (
        ply_header(
            len(pts(c)),
            extra=f"element vertex {len(pts(c))}\nproperty double x\n"
            "property double y\nproperty double z",
        )
        + pts(c).astype("<f8").tobytes() * 2
    ),
    expect={2, 0},
    result="full",
    keep_truth=True,
    note="ambiguous file: refusing is safest; reading the first element is tolerable",
)
bad_scan(
    "ply-unknown-type",
    "property quux x",
    B,
    lambda c: (
        ply_header(len(pts(c)), props=[("quux", "x"), ("double", "y"), ("double", "z")])
        + pts(c).astype("<f8").tobytes()
    ),
)
bad_scan(
    "ply-nul-header",
    "NUL bytes inside the header",
    B,
    lambda c: ply_binary(pts(c)).replace(b"comment bad_input corpus", b"comment \x00\x00\x00"),
    expect={2, 0},
    result="full",
    keep_truth=True,
    note="a NUL in a comment is harmless",
)
bad_scan(
    "ply-bom",
    "UTF-8 BOM before 'ply'",
    B,
    lambda c: b"\xef\xbb\xbf" + ply_ascii(pts(c)),
    expect={2, 0},
    result="full",
    keep_truth=True,
)


def _ascii_with(ctx, row: int, text: str):
    lines = ply_ascii(pts(ctx)).decode().split("\n")
    hdr = lines.index("end_header")
    lines[hdr + 1 + row] = text
    return "\n".join(lines).encode()


for cid, tok in [
    ("nan", "nan"),
    ("NaN-caps", "NaN"),
    ("minus-nan", "-nan"),
    ("inf", "inf"),
    ("plus-inf", "+Infinity"),
    ("1e999", "1e999"),
    ("-1e999", "-1e999"),
]:
    bad_scan(
        f"ply-ascii-{cid}",
        f"ascii PLY, one row '{tok} 0 0'",
        B,
        lambda c, tok=tok: _ascii_with(c, 50, f"{tok} 0.1 0.2"),
        expect={0, 2},
        result="full",
        keep_truth=True,
        warn=[B],
        note="README: a corrupt value is an error naming the file and line; dropping "
        "the row is acceptable only with a warning",
    )
for cid, tok in [
    ("word", "abc 0.1 0.2"),
    ("comma", "0,1 0,2 0,3"),
    ("two-values", "0.1 0.2"),
    ("four-values", "0.1 0.2 0.3 0.4"),
    ("double-dot", "0.1.2 0.2 0.3"),
    ("empty-line", ""),
    ("hex", "0x1p-3 0.2 0.3"),
]:
    bad_scan(
        f"ply-ascii-bad-{cid}",
        f"ascii PLY, one bad row {tok!r}",
        B,
        lambda c, tok=tok: _ascii_with(c, 50, tok),
        culprit=[B],
    )


def _nan_binary(ctx, vals):
    p = pts(ctx).copy()
    p[10 : 10 + len(vals), 0] = vals
    return ply_binary(p)


bad_scan(
    "ply-bin-nan",
    "binary PLY, 5 NaN rows",
    B,
    lambda c: _nan_binary(c, [np.nan] * 5),
    expect={0, 2},
    result="full",
    keep_truth=True,
    warn=[B],
    note="NaN rows: refuse or drop with a word",
)
bad_scan(
    "ply-bin-inf",
    "binary PLY, one inf value",
    B,
    lambda c: _nan_binary(c, [np.inf]),
    expect={0, 2},
    result="full",
    keep_truth=True,
    warn=[B],
)
bad_scan(
    "ply-bin-all-nan",
    "binary PLY, every value NaN",
    B,
    lambda c: ply_binary(np.full((3000, 3), np.nan)),
)
bad_scan(
    "ply-identical",
    "all points identical",
    B,
    lambda c: ply_binary(np.tile([[0.1, 0.2, 0.3]], (3000, 1))),
)
bad_scan(
    "ply-0-points",
    "0 vertices",
    B,
    lambda c: ply_binary(np.zeros((0, 3))),
    expect={2, 3},
    note="README: empty file -> 2, fewer than min_points -> 3 (named); either, named",
)
for k in (1, 2, 3):
    bad_scan(
        f"ply-{k}-points",
        f"{k} vertices",
        B,
        lambda c, k=k: ply_binary(pts(c)[:k]),
        expect={3},
        note="README: fewer than min_points (100) valid points -> left out, exit 3, named",
    )
bad_scan(
    "ply-99-points",
    "99 vertices (min_points - 1)",
    B,
    lambda c: ply_binary(pts(c)[:99]),
    expect={3},
)


def _stray(ctx, v):
    p = np.vstack([pts(ctx), [[v, v, v]]])
    return ply_binary(p)


good_scan(
    "ply-stray-1e9",
    "3000 good points plus 1 stray point at 1e9",
    B,
    lambda c: _stray(c, 1e9),
    note="one wild point must not wreck the scan",
)
good_scan(
    "ply-stray-1e300",
    "3000 good points plus 1 stray point at 1e300",
    B,
    lambda c: _stray(c, 1e300),
    expect={0, 2},
    note="1e300 overflows squared distances; refuse naming it, or cope",
)
good_scan(
    "ply-dup-points",
    "every point written twice",
    B,
    lambda c: ply_binary(np.repeat(pts(c), 2, axis=0)),
)

# ---------------------------------------------------------------- PCD
good_scan("pcd-ascii", "PCD ascii", "scan_003.pcd", lambda c: pcd_bytes(pts(c), "ascii"))
good_scan(
    "pcd-binary",
    "PCD binary, float64 (SIZE 8 TYPE F)",
    "scan_003.pcd",
    lambda c: pcd_bytes(pts(c), "binary"),
    note="valid PCD: 8-byte floats are allowed",
)
good_scan(
    "pcd-binary-f32",
    "PCD binary, float32",
    "scan_003.pcd",
    lambda c: pcd_header(len(pts(c)), "binary", size="4 4 4") + pts(c).astype("<f4").tobytes(),
)
good_scan(
    "pcd-compressed-f32",
    "PCD binary_compressed, float32",
    "scan_003.pcd",
    lambda c: (
        lambda soa: (
            pcd_header(len(pts(c)), "binary_compressed", size="4 4 4")
            + len(lzf_literal(soa)).to_bytes(4, "little")
            + len(soa).to_bytes(4, "little")
            + lzf_literal(soa)
        )
    )(np.ascontiguousarray(pts(c).astype("<f4").T).tobytes()),
)
good_scan(
    "pcd-compressed",
    "PCD binary_compressed (LZF), float64",
    "scan_003.pcd",
    lambda c: pcd_bytes(pts(c), "binary_compressed"),
)


def _pcd_organized(ctx):
    p = pts(ctx).copy()
    n = len(p) // 10 * 10
    p = p[:n]
    p[::7] = np.nan  # no-return cells of an organized cloud
    return pcd_header(n, "binary", width=n // 10, height=10) + p.astype("<f8").tobytes()


good_scan(
    "pcd-organized-nan",
    "organized PCD (W x H) with NaN no-return cells",
    "scan_003.pcd",
    _pcd_organized,
    note="NaN cells are how organized PCD stores no return: normal data",
)


def _pcd_rgb(ctx):
    p = pts(ctx).astype("<f4")
    a = np.zeros(len(p), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgb", "<f4")])
    a["x"], a["y"], a["z"] = p.T
    a["rgb"] = np.frombuffer(np.full(len(p), 0x00FF8000, "<u4").tobytes(), "<f4")
    return pcd_header(len(p), "binary", "x y z rgb", "4 4 4 4", "F F F F", "1 1 1 1") + a.tobytes()


good_scan("pcd-rgb-f32", "PCD binary float32 with packed rgb", "scan_003.pcd", _pcd_rgb)
PB = "scan_003.pcd"
bad_scan(
    "pcd-points-mismatch",
    "POINTS != WIDTH*HEIGHT",
    PB,
    lambda c: pcd_bytes(pts(c), "binary").replace(
        f"POINTS {len(pts(c))}".encode(), f"POINTS {len(pts(c)) - 10}".encode()
    ),
)
bad_scan(
    "pcd-no-data",
    "no DATA line",
    PB,
    lambda c: pcd_bytes(pts(c), "ascii").replace(b"DATA ascii\n", b""),
)
bad_scan(
    "pcd-truncated-binary",
    "binary PCD cut short",
    PB,
    lambda c: pcd_bytes(pts(c), "binary")[:-5000],
)
bad_scan(
    "pcd-comp-bad-sizes",
    "binary_compressed with lying sizes",
    PB,
    lambda c: pcd_bytes(pts(c), "binary_compressed").replace(
        b"DATA binary_compressed\n", b"DATA binary_compressed\n\xff\xff\x00\x00\x10\x00\x00\x00", 1
    )[:-100],
)
bad_scan(
    "pcd-comp-garbage",
    "binary_compressed with random payload",
    PB,
    lambda c: (
        pcd_header(3000, "binary_compressed")
        + (20000).to_bytes(4, "little")
        + (72000).to_bytes(4, "little")
        + np.random.default_rng(1).bytes(20000)
    ),
)
bad_scan(
    "pcd-unknown-data",
    "DATA binary_zstd",
    PB,
    lambda c: pcd_bytes(pts(c), "binary").replace(b"DATA binary", b"DATA binary_zstd"),
)
bad_scan(
    "pcd-no-z",
    "FIELDS x y (no z)",
    PB,
    lambda c: (
        pcd_header(len(pts(c)), "ascii", "x y", "8 8", "F F", "1 1")
        + fmt_rows(pts(c)[:, :2]).encode()
    ),
)
bad_scan(
    "pcd-size-mismatch",
    "SIZE lists 2 sizes for 3 fields",
    PB,
    lambda c: pcd_bytes(pts(c), "ascii").replace(b"SIZE 8 8 8", b"SIZE 8 8"),
)
bad_scan(
    "pcd-ascii-nan",
    "ascii PCD, one row 'nan nan nan' (unorganized)",
    PB,
    lambda c: _pcd_ascii_row(c, "nan nan nan"),
    expect={0, 2},
    result="full",
    keep_truth=True,
    warn=[PB],
    note="an unorganized PCD with a NaN row: refuse or drop with a word",
)
bad_scan(
    "pcd-ascii-1e999",
    "ascii PCD, one value 1e999",
    PB,
    lambda c: _pcd_ascii_row(c, "1e999 0.1 0.2"),
    expect={0, 2},
    result="full",
    keep_truth=True,
    warn=[PB],
)
bad_scan(
    "pcd-ascii-extra-col",
    "ascii PCD, one row with 4 values",
    PB,
    lambda c: _pcd_ascii_row(c, "0.1 0.2 0.3 0.4"),
)
bad_scan("pcd-ascii-word", "ascii PCD, one row 'x y z'", PB, lambda c: _pcd_ascii_row(c, "x y z"))
bad_scan(
    "pcd-garbage", "random bytes named .pcd", PB, lambda c: np.random.default_rng(2).bytes(50000)
)
bad_scan(
    "pcd-points-huge",
    "binary PCD with POINTS/WIDTH 10^12",
    PB,
    lambda c: pcd_header(10**12, "binary") + pts(c).astype("<f8").tobytes(),
)


def _pcd_ascii_row(ctx, row):
    b = pcd_bytes(pts(ctx), "ascii").decode().split("\n")
    i = next(k for k, ln in enumerate(b) if ln.startswith("DATA")) + 40
    b[i] = row
    return "\n".join(b).encode()
