"""Hostile-input corpus, family 1 (continued): XYZ/PTS, NPY, E57, LAS/LAZ, file system.
The cases are added to bad_input_cases_scans.CASES."""

from __future__ import annotations

import os

import numpy as np

from bench.bad_input import (
    fmt_rows,
    npy_bytes,
    ply_binary,
    ply_header,
    pts_bytes,
    write_e57,
    write_las,
)
from bench.bad_input_cases_scans import (  # noqa: F401
    CASES,
    REG,
    B,
    P,
    add,
    bad_scan,
    good_scan,
    pts,
)

# ---------------------------------------------------------------- XYZ / PTS / TXT
XB = "scan_003.xyz"
good_scan("xyz-valid", "XYZ text", XB, lambda c: fmt_rows(pts(c)).encode())
good_scan("xyz-tabs", "XYZ with tab separators", XB, lambda c: fmt_rows(pts(c), sep="\t").encode())
good_scan("xyz-crlf", "XYZ with CRLF", XB, lambda c: fmt_rows(pts(c), nl="\r\n").encode())
good_scan(
    "xyz-sci",
    "XYZ in %e notation",
    XB,
    lambda c: "".join(f"{a:e} {b:e} {d:e}\n" for a, b, d in pts(c)).encode(),
)
good_scan(
    "xyzn-valid",
    "XYZN (x y z nx ny nz)",
    "scan_003.xyzn",
    lambda c: fmt_rows(np.hstack([pts(c), np.tile([0, 0, 1.0], (len(pts(c)), 1))])).encode(),
)
good_scan(
    "xyzrgb-valid",
    "XYZRGB (colors 0..1)",
    "scan_003.xyzrgb",
    lambda c: fmt_rows(np.hstack([pts(c), np.full((len(pts(c)), 3), 0.5)])).encode(),
)
good_scan(
    "xyz-trailing-blank",
    "XYZ with trailing blank lines",
    XB,
    lambda c: fmt_rows(pts(c)).encode() + b"\n\n\n",
)
bad_scan("xyz-2-cols", "XYZ with 2 columns", XB, lambda c: fmt_rows(pts(c)[:, :2]).encode())
bad_scan(
    "xyz-4-cols",
    "XYZ with 4 columns (x y z intensity)",
    XB,
    lambda c: fmt_rows(np.hstack([pts(c), np.ones((len(pts(c)), 1))])).encode(),
    expect={0, 2},
    result="full",
    keep_truth=True,
    note="extra column: read x y z or refuse by name",
)
bad_scan(
    "xyz-mixed-cols",
    "XYZ, one row with 4 values among 3-value rows",
    XB,
    lambda c: fmt_rows(pts(c)).replace("\n", "\n0.1 0.2 0.3 0.4\n", 1).encode(),
)
bad_scan(
    "xyz-comma",
    "comma-separated XYZ",
    XB,
    lambda c: fmt_rows(pts(c), sep=",").encode(),
    expect={0, 2},
    result="full",
    keep_truth=True,
    note="CSV-ish XYZ: read correctly or refuse by name; misreading is BAD via poses",
)
bad_scan(
    "xyz-header",
    "XYZ with a header line 'x y z'",
    XB,
    lambda c: b"x y z\n" + fmt_rows(pts(c)).encode(),
    expect={0, 2},
    result="full",
    keep_truth=True,
    warn=[XB],
    note="a header row dropped silently is POOR",
)
bad_scan(
    "xyz-comment",
    "XYZ with a '# scanner 1' comment line",
    XB,
    lambda c: b"# scanner 1\n" + fmt_rows(pts(c)).encode(),
    expect={0, 2},
    result="full",
    keep_truth=True,
)
bad_scan(
    "xyz-1e999",
    "XYZ, one value 1e999",
    XB,
    lambda c: fmt_rows(pts(c)).replace("\n", "\n1e999 0.1 0.2\n", 1).encode(),
    expect={0, 2},
    result="full",
    keep_truth=True,
    warn=[XB],
    note="README: corrupt value -> error naming the line; silent drop is POOR",
)
bad_scan(
    "xyz-nan",
    "XYZ, one row nan nan nan",
    XB,
    lambda c: fmt_rows(pts(c)).replace("\n", "\nnan nan nan\n", 1).encode(),
    expect={0, 2},
    result="full",
    keep_truth=True,
    warn=[XB],
)
bad_scan(
    "xyz-word",
    "XYZ, one token 'abc'",
    XB,
    lambda c: fmt_rows(pts(c)).replace("\n", "\nabc 0.1 0.2\n", 1).encode(),
)
bad_scan("xyz-empty", "empty XYZ", XB, lambda c: b"")
bad_scan("xyz-whitespace", "XYZ of blank lines only", XB, lambda c: b"\n \n\t\n")
bad_scan("xyz-utf16", "XYZ encoded as UTF-16", XB, lambda c: fmt_rows(pts(c)).encode("utf-16"))
bad_scan("xyz-1-row", "XYZ with one point", XB, lambda c: b"0.1 0.2 0.3\n", expect={3})
bad_scan(
    "xyz-blank-middle",
    "XYZ with a blank line in the middle",
    XB,
    lambda c: fmt_rows(pts(c)).replace("\n", "\n\n", 1).encode(),
    expect={0, 2},
    result="full",
    keep_truth=True,
)
PT = "scan_003.pts"
good_scan("pts-valid", "PTS with count line", PT, lambda c: pts_bytes(pts(c)))
good_scan("pts-4-cols", "PTS x y z intensity", PT, lambda c: pts_bytes(pts(c), extra_cols=1))
good_scan("pts-7-cols", "PTS x y z i r g b", PT, lambda c: pts_bytes(pts(c), extra_cols=4))
bad_scan(
    "pts-count-small",
    "PTS count line smaller than the rows",
    PT,
    lambda c: pts_bytes(pts(c), count=len(pts(c)) - 100),
)
bad_scan(
    "pts-count-large",
    "PTS count line larger than the rows",
    PT,
    lambda c: pts_bytes(pts(c), count=len(pts(c)) + 100),
)
bad_scan(
    "pts-count-word", "PTS count line 'abc'", PT, lambda c: b"abc\n" + fmt_rows(pts(c)).encode()
)
bad_scan(
    "pts-no-count",
    "PTS without the count line",
    PT,
    lambda c: fmt_rows(pts(c)).encode(),
    expect={0, 2},
    result="full",
    keep_truth=True,
    note="the first row would be read as a count: refuse or read all, never misread",
)
bad_scan(
    "pts-1e999",
    "PTS, one value 1e999",
    PT,
    lambda c: (
        pts_bytes(pts(c))
        .replace(b"\n", b"\n1e999 1 1\n", 2)
        .replace(f"{len(pts(c))}\n1e999 1 1\n".encode(), f"{len(pts(c)) + 1}\n".encode(), 1)
    ),
    expect={0, 2},
    result="full",
    keep_truth=True,
    warn=[PT],
)

# ---------------------------------------------------------------- NPY
NB = "scan_003.npy"
good_scan("npy-f64", "NPY (N, 3) float64", NB, lambda c: npy_bytes(pts(c)))
good_scan("npy-f32", "NPY (N, 3) float32", NB, lambda c: npy_bytes(pts(c).astype(np.float32)))
good_scan(
    "npy-n6",
    "NPY (N, 6) (x y z + colors)",
    NB,
    lambda c: npy_bytes(np.hstack([pts(c), np.full((len(pts(c)), 3), 0.5)])),
)
good_scan("npy-fortran", "NPY Fortran order", NB, lambda c: npy_bytes(np.asfortranarray(pts(c))))
good_scan("npy-big-endian", "NPY >f8", NB, lambda c: npy_bytes(pts(c).astype(">f8")))
bad_scan(
    "npy-int",
    "NPY int64 (N, 3) (rounded: collapses the scan)",
    NB,
    lambda c: npy_bytes(np.round(pts(c)).astype(np.int64)),
    expect={2, 3},
    note="int coordinates are legal but here collapse the scan: refuse or leave out, named",
)
bad_scan(
    "npy-float16",
    "NPY float16",
    NB,
    lambda c: npy_bytes(pts(c).astype(np.float16)),
    expect={0, 2, 3},
    note="float16 is a legal dtype; quantized to ~1e-3",
)
bad_scan(
    "npy-n4", "NPY (N, 4)", NB, lambda c: npy_bytes(np.hstack([pts(c), np.ones((len(pts(c)), 1))]))
)
bad_scan("npy-transposed", "NPY (3, N)", NB, lambda c: npy_bytes(pts(c).T.copy()))
bad_scan("npy-1d", "NPY 1-D", NB, lambda c: npy_bytes(pts(c).ravel()))
bad_scan("npy-0d", "NPY 0-d scalar", NB, lambda c: npy_bytes(np.array(3.0)))
bad_scan("npy-3d", "NPY (1, N, 3)", NB, lambda c: npy_bytes(pts(c)[None]))
bad_scan("npy-complex", "NPY complex128 (N, 3)", NB, lambda c: npy_bytes(pts(c).astype(complex)))
bad_scan("npy-bool", "NPY bool (N, 3)", NB, lambda c: npy_bytes(pts(c) > 0))
bad_scan("npy-str", "NPY unicode strings (N, 3)", NB, lambda c: npy_bytes(pts(c).astype(str)))
bad_scan(
    "npy-structured",
    "NPY structured dtype x,y,z",
    NB,
    lambda c: npy_bytes(np.rec.fromarrays(pts(c).T, names="x,y,z")),
    expect={0, 2},
    result="full",
    keep_truth=True,
)


class _Pwn:
    def __reduce__(self):
        return (os.system, ("touch PWNED_BY_PICKLE",))


def _pickled(ctx):
    a = np.empty(2, dtype=object)
    a[0], a[1] = _Pwn(), 1
    return npy_bytes(a)


def _no_pwn(ctx, run):
    return (
        [("BAD", "a pickled .npy was unpickled: code ran")]
        if (ctx.work / "PWNED_BY_PICKLE").exists()
        else []
    )


add(
    "npy-object-pickle",
    "scan-files",
    "NPY object dtype whose pickle runs a command",
    lambda c: (c.scans(), c.replace(3, NB, _pickled(c))),
    REG,
    {2},
    culprit=[NB],
    check=_no_pwn,
)
bad_scan("npy-text", "a text file named .npy", NB, lambda c: fmt_rows(pts(c)).encode())
bad_scan("npy-truncated", "NPY cut short", NB, lambda c: npy_bytes(pts(c))[:-1001])


def _npy_lying_header(ctx):
    body = pts(ctx).astype("<f8").tobytes()
    hdr = "{'descr': '<f8', 'fortran_order': False, 'shape': (99999999999, 3), }"
    hdr = hdr + " " * (118 - len(hdr)) + "\n"
    return b"\x93NUMPY\x01\x00" + len(hdr).to_bytes(2, "little") + hdr.encode() + body


bad_scan("npy-header-lies", "NPY header shape (99999999999, 3), small body", NB, _npy_lying_header)
bad_scan(
    "npy-nan-row",
    "NPY with a NaN row",
    NB,
    lambda c: npy_bytes(np.vstack([pts(c), [[np.nan] * 3]])),
    expect={0, 2},
    result="full",
    keep_truth=True,
    warn=[NB],
)
bad_scan(
    "npy-inf-row",
    "NPY with an inf value",
    NB,
    lambda c: npy_bytes(np.vstack([pts(c), [[np.inf, 0, 0]]])),
    expect={0, 2},
    result="full",
    keep_truth=True,
    warn=[NB],
)
bad_scan("npy-empty", "NPY (0, 3)", NB, lambda c: npy_bytes(np.zeros((0, 3))), expect={2, 3})
bad_scan("npy-2-points", "NPY (2, 3)", NB, lambda c: npy_bytes(pts(c)[:2]), expect={3})
bad_scan(
    "npz-in-folder",
    "an .npz (not a scan format) beside valid scans",
    "scan_003.npz",
    lambda c: b"PK\x03\x04junk",
    expect={0, 3},
    result="any",
    warn=["scan_003.npz"],
    culprit=[],
    note="README: unknown files are skipped with a warning naming them; the other 7 scans "
    "then register as the 7-scan set without scan_003 does (4 of 7 at seed 1: exit 3)",
)

# ---------------------------------------------------------------- E57
EB = "scan_003.e57"


def _e57_bytes(ctx, clouds):
    p = ctx.work / "tmp.e57"
    write_e57(p, clouds)
    b = p.read_bytes()
    p.unlink()
    return b


good_scan("e57-valid", "E57 with one scan", EB, lambda c: _e57_bytes(c, [pts(c)]))
bad_scan(
    "e57-garbage", "random bytes named .e57", EB, lambda c: np.random.default_rng(3).bytes(40000)
)
bad_scan(
    "e57-half",
    "a valid E57 cut in half",
    EB,
    lambda c: (lambda b: b[: len(b) // 2])(_e57_bytes(c, [pts(c)])),
)
bad_scan(
    "e57-tail-cut",
    "a valid E57 with its last 100 bytes cut",
    EB,
    lambda c: _e57_bytes(c, [pts(c)])[:-100],
)
bad_scan("e57-zero", "zero-size .e57", EB, lambda c: b"")
bad_scan(
    "e57-flipped-byte",
    "a valid E57 with one byte flipped in the middle (CRC)",
    EB,
    lambda c: (lambda b: b[: len(b) // 2] + bytes([b[len(b) // 2] ^ 0xFF]) + b[len(b) // 2 + 1 :])(
        _e57_bytes(c, [pts(c)])
    ),
)


def _e57_two(ctx):
    ctx.scans(skip=(3, 4))
    (ctx.inp / "pair.e57").write_bytes(_e57_bytes(ctx, [ctx.pts(3), ctx.pts(4)]))
    gt = ctx.gt()
    ctx.truth["pair.e57#0"] = gt["scan_003.ply"]
    ctx.truth["pair.e57#1"] = gt["scan_004.ply"]


add(
    "e57-two-scans",
    "scan-files",
    "one E57 file holding two scans (named file.e57#k)",
    _e57_two,
    REG,
    {0},
    expect_result="full",
)


def _e57_all(ctx):
    ctx.inp.mkdir()
    (ctx.inp / "all.e57").write_bytes(_e57_bytes(ctx, [ctx.pts(i) for i in range(8)]))
    gt = ctx.gt()
    ctx.truth = {f"all.e57#{i}": gt[f"scan_{i:03d}.ply"] for i in range(8)}


add(
    "e57-all-in-one",
    "scan-files",
    "all 8 scans in one E57 file",
    _e57_all,
    REG,
    {0},
    expect_result="full",
)

# ---------------------------------------------------------------- LAS / LAZ


def _las_bytes(ctx, laz=False, **kw):
    p = ctx.work / ("tmp.laz" if laz else "tmp.las")
    write_las(p, pts(ctx), laz=laz, **kw)
    b = p.read_bytes()
    p.unlink()
    return b


good_scan("las-valid", "LAS 1.4", "scan_003.las", lambda c: _las_bytes(c))
good_scan("laz-valid", "LAZ 1.4", "scan_003.laz", lambda c: _las_bytes(c, laz=True))
bad_scan(
    "las-garbage",
    "random bytes named .las",
    "scan_003.las",
    lambda c: np.random.default_rng(4).bytes(30000),
)
bad_scan("las-truncated", "LAS cut short", "scan_003.las", lambda c: _las_bytes(c)[:-5000])
bad_scan(
    "laz-truncated", "LAZ cut short", "scan_003.laz", lambda c: _las_bytes(c, laz=True)[:-3000]
)
bad_scan("laz-zero", "zero-size .laz", "scan_003.laz", lambda c: b"")
bad_scan(
    "las-header-only",
    "LAS header only (points missing)",
    "scan_003.las",
    lambda c: _las_bytes(c)[:375],
)


def _las_count_lies(ctx):
    b = bytearray(_las_bytes(ctx))
    # LAS 1.4: legacy count at 107 (uint32), 64-bit count at 247 (uint64)
    n = int.from_bytes(b[247:255], "little")
    b[247:255] = (n * 10).to_bytes(8, "little")
    b[107:111] = min(n * 10, 2**32 - 1).to_bytes(4, "little")
    return bytes(b)


bad_scan("las-count-lies", "LAS header claims 10x the points", "scan_003.las", _las_count_lies)
good_scan(
    "las-coarse",
    "LAS with scale 1e-3 (coarse quantization, diag ~1.4)",
    "scan_003.las",
    lambda c: _las_bytes(c, scale=1e-3),
    note="quantized to 1 mm on a 1.4-unit object",
)

# ---------------------------------------------------------------- file system oddities
bad_scan("empty-ply", "zero-size scan_003.ply", B, lambda c: b"")


def _fs_case(
    cid, desc, fn, expect, culprit=None, result="any", warn=None, note="", skip=None, argv=None
):
    add(
        cid,
        "file-system",
        desc,
        fn,
        argv or REG,
        set(expect),
        culprit=culprit or [],
        expect_result=result,
        expect_warn=warn or [],
        note=note,
        skip=skip,
    )


def _dir_named_ply(ctx):
    ctx.scans()
    ctx.replace(3, B, None)
    (ctx.inp / B).mkdir()


_fs_case(
    "dir-named-ply",
    "a directory named scan_003.ply",
    _dir_named_ply,
    {0, 2, 3},
    culprit=[B],
    warn=[B],
    note="README: a sub-folder is not read, with a warning naming it; the other 7 scans "
    "then register as the 7-scan set without scan_003 does (4 of 7 at seed 1: exit 3)",
)


def _dangling(ctx):
    ctx.scans()
    ctx.replace(3, B, None)
    os.symlink("/nonexistent/scan.ply", ctx.inp / B)


_fs_case("symlink-dangling", "dangling symlink scan_003.ply", _dangling, {2}, culprit=[B])


def _loop(ctx):
    ctx.scans()
    ctx.replace(3, B, None)
    os.symlink("loop_b.ply", ctx.inp / B)
    os.symlink(B, ctx.inp / "loop_b.ply")


_fs_case(
    "symlink-loop",
    "symlink loop scan_003.ply <-> loop_b.ply",
    _loop,
    {2},
    culprit=[B, "loop_b.ply"],
)


def _good_link(ctx):
    ctx.scans()
    ctx.replace(3, B, None, keep_truth=True)
    (ctx.work / "elsewhere").mkdir()
    ctx.write_scan(ctx.work / "elsewhere", 3, "ply")
    os.symlink(ctx.work / "elsewhere" / B, ctx.inp / B)
    ctx.truth[B] = ctx.gt()[B]
    ctx.inputs.append(ctx.work / "elsewhere")


_fs_case(
    "symlink-valid",
    "scan_003.ply a symlink to a valid scan elsewhere",
    _good_link,
    {0},
    result="full",
)


def _chmod000(ctx):
    ctx.scans()
    os.chmod(ctx.inp / B, 0)
    ctx.cleanup.append(lambda: os.chmod(ctx.inp / B, 0o644))


_fs_case(
    "chmod-000",
    "scan_003.ply with mode 000",
    _chmod000,
    {2},
    culprit=[B],
    skip=lambda c: "running as root: chmod 000 does not stop reads" if os.geteuid() == 0 else None,
)


def _unknown_ext(ctx):
    ctx.scans()
    (ctx.inp / "notes.foo").write_bytes(b"hello")


_fs_case(
    "unknown-ext",
    "an unknown extension file beside the scans",
    _unknown_ext,
    {0},
    warn=["notes.foo"],
    result="full",
)


def _bytes_name(ctx):
    ctx.scans()
    ctx.replace(3, B, None)
    with open(os.path.join(os.fsencode(ctx.inp), b"scan_\xff\xfe.ply"), "wb") as f:
        f.write(ply_binary(ctx.pts(3)))


_fs_case(
    "undecodable-name",
    "a scan whose name is not UTF-8 (b'scan_\\xff\\xfe.ply')",
    _bytes_name,
    {2},
    culprit=["scan_", "\\xff", "undecodable"],
    note="README: an undecodable name is an error naming the file",
)


def _long_name(ctx):
    ctx.scans()
    name = "scan_003_" + "x" * 230 + ".ply"
    ctx.replace(3, name, ply_binary(ctx.pts(3)))
    ctx.truth[name] = ctx.gt()[B]


_fs_case("long-name", "a 243-character scan name", _long_name, {0}, result="full")


def _odd_names(ctx):
    ctx.scans()
    gt = ctx.gt()
    for i, nm in [(3, "scän 3 (copy).ply"), (4, "-scan4.ply"), (5, "scan 5;rm -rf.ply")]:
        ctx.replace(i, nm, None)
        (ctx.inp / f"scan_{i:03d}.ply").unlink(missing_ok=True)
        ctx.write_scan(ctx.inp, i, "ply", stem=nm[:-4])
        ctx.truth[nm] = gt[f"scan_{i:03d}.ply"]


_fs_case(
    "odd-names", "names with unicode, spaces, a leading '-' and ';'", _odd_names, {0}, result="full"
)


def _newline_name(ctx):
    ctx.scans()
    ctx.replace(3, "scan\n003.ply", ply_binary(ctx.pts(3)))
    ctx.truth["scan\n003.ply"] = ctx.gt()[B]


_fs_case(
    "newline-name",
    "a scan name containing a newline",
    _newline_name,
    {0, 2},
    culprit=["scan"],
    result="full",
)


def _mixed(ctx):
    ctx.inp.mkdir()
    gt = ctx.gt()
    ctx.truth = {}
    for i, fmt in enumerate(["ply", "ply_ascii", "pcd", "xyz", "npy", "las", "e57", "pts"]):
        nm = ctx.write_scan(ctx.inp, i, fmt)
        ctx.truth[nm] = gt[f"scan_{i:03d}.ply"]


_fs_case(
    "mixed-formats",
    "8 scans in 8 formats (ply, ascii ply, ascii pcd, xyz, npy, las, e57, pts)",
    _mixed,
    {0},
    result="full",
)


def _hidden(ctx):
    ctx.scans()
    (ctx.inp / ".DS_Store").write_bytes(b"\x00\x01junk")
    (ctx.inp / "._scan_003.ply").write_bytes(b"AppleDouble junk")
    (ctx.inp / ".hidden.ply").write_bytes(ply_binary(ctx.pts(3)[:50]))


_fs_case(
    "hidden-files",
    "hidden junk files (.DS_Store, ._scan_003.ply, .hidden.ply)",
    _hidden,
    {0},
    result="full",
    note="README: hidden files are skipped silently",
)


def _dup_scan(ctx):
    ctx.scans()
    ctx.write_scan(ctx.inp, 3, "ply", stem="scan_008")
    ctx.truth["scan_008.ply"] = ctx.gt()[B]


_fs_case(
    "duplicate-scan",
    "scan_003 copied as scan_008 (two identical scans)",
    _dup_scan,
    {0, 3},
    result="any",
    note="identical scans: registering both at one pose, or naming the duplicate",
)


def _one(ctx):
    ctx.scans(n=1)


_fs_case("one-scan", "a folder with one scan", _one, {2}, culprit=["in", "scan", "2"])
_fs_case("empty-folder", "an empty folder", lambda c: c.inp.mkdir(), {2}, culprit=["in"])
_fs_case(
    "nonexistent-folder",
    "a folder that does not exist",
    None,
    {2},
    culprit=["nope"],
    argv=["register", "{work}/nope", "--out", "{out}"],
)


def _file_not_folder(ctx):
    ctx.scans()


_fs_case(
    "file-not-folder",
    "a scan file given instead of a folder",
    _file_not_folder,
    {2},
    culprit=["scan_000.ply"],
    argv=["register", "{inp}/scan_000.ply", "--out", "{out}"],
)


def _only_sidecars(ctx):
    ctx.inp.mkdir()
    (ctx.inp / "ground_truth.json").write_text("{}")
    (ctx.inp / "README.md").write_text("hi")
    (ctx.inp / "data.txt").write_text("1 2 3\n")


_fs_case(
    "only-sidecars",
    "a folder of ground_truth.json, README.md, data.txt only",
    _only_sidecars,
    {2},
    culprit=["in", "no scan", "scans"],
)


def _nested(ctx):
    ctx.scans(folder=ctx.inp / "sub")


_fs_case("nested-only", "scans only in a sub-folder", _nested, {2}, culprit=["in", "sub"])


def _fifo(ctx):
    ctx.scans()
    ctx.replace(3, B, None)
    os.mkfifo(ctx.inp / B)


_fs_case(
    "fifo",
    "scan_003.ply is a FIFO (reading it would block forever)",
    _fifo,
    {2},
    culprit=[B],
    note="must not hang",
)


def _devzero(ctx):
    ctx.scans()
    ctx.replace(3, B, None)
    os.symlink("/dev/zero", ctx.inp / B)


_fs_case(
    "dev-zero",
    "scan_003.ply -> /dev/zero (endless)",
    _devzero,
    {2},
    culprit=[B],
    note="must not hang or fill memory",
)


def _sparse_giant(ctx):
    ctx.scans()
    ctx.replace(3, B, None)
    n = 1_000_000_000
    with open(ctx.inp / B, "wb") as f:
        f.write(ply_header(n))
        f.truncate(len(ply_header(n)) + n * 24)


_fs_case(
    "sparse-giant",
    "a sparse 24 GB PLY claiming 10^9 vertices (zeros)",
    _sparse_giant,
    {2},
    culprit=[B],
    note="README: more than max_points_per_scan (50 million) -> error, quickly",
)


def _hardlink(ctx):
    ctx.scans()
    os.link(ctx.inp / "scan_002.ply", ctx.inp / "scan_002b.ply")
    ctx.truth["scan_002b.ply"] = ctx.gt()["scan_002.ply"]


_fs_case("hardlink-dup", "scan_002b.ply a hard link of scan_002.ply", _hardlink, {0, 3})


def _txt_scan(ctx):
    ctx.scans()
    ctx.replace(3, "scan_003.txt", fmt_rows(ctx.pts(3)).encode())


_fs_case(
    "txt-scan",
    ".txt point file beside the scans (not a supported suffix)",
    _txt_scan,
    {0, 3},
    warn=["scan_003.txt"],
    note="README: unsupported files skipped with a warning",
)
