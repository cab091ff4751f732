"""Hostile-input corpus, families 2-3 and 7: units and frames, ground truth, sequences."""

from __future__ import annotations

import json
import shutil

import numpy as np

from bench.bad_input import Case, Ctx

REG = ["register", "{inp}", "--out", "{out}"]
CASES: list[Case] = []


def add(*a, **k) -> None:
    CASES.append(Case(*a, **k))


# ---------------------------------------------------------------- 2. units and frames


def units(cid, desc, scale=1.0, offset=None, fmt="ply", expect=frozenset({0}), twin=True, note=""):
    def setup(ctx: Ctx):
        ctx.scans(fmt=fmt, scale=scale, offset=offset)
        if twin:
            ctx.twin = ctx.fx["clean_registered"]

    add(
        cid,
        "units",
        desc,
        setup,
        REG,
        set(expect),
        expect_result="full" if twin else "any",
        note=note
        or "compared with the clean twin (same scans, original units): same count, "
        "rotations within 2 deg of the truth",
    )


UTM = [512345.6, 4123456.7, 87.5]
units("units-mm", "all scans x1000 (millimetres)", scale=1000.0)
units("units-km", "all scans x1e-3 (kilometres)", scale=1e-3)
units("units-1e-6", "all scans x1e-6", scale=1e-6)
units("units-1e6", "all scans x1e6", scale=1e6)
units("units-mm-ascii", "all scans x1000, ascii PLY", scale=1000.0, fmt="ply_ascii")
units(
    "offset-round-1e6",
    "every scan shifted by [1e6, 1e6, 0] (georeferenced, round)",
    offset=[1e6, 1e6, 0.0],
)
units("offset-utm", "every scan shifted by [512345.6, 4123456.7, 87.5] (UTM-like)", offset=UTM)
units(
    "offset-utm-negative",
    "every scan shifted by [-512345.6, -4123456.7, -87.5]",
    offset=[-v for v in UTM],
)
units(
    "offset-utm-ascii", "UTM-like offset, ascii PLY (repr precision)", offset=UTM, fmt="ply_ascii"
)
units(
    "offset-utm-mm",
    "millimetres and a UTM-like offset in mm",
    scale=1000.0,
    offset=[v * 1000 for v in UTM],
)
units("offset-utm-las", "UTM-like offset, LAS files (scale 1e-5)", offset=UTM, fmt="las")
units("offset-utm-npy", "UTM-like offset, NPY files", offset=UTM, fmt="npy")
units("offset-1e9", "every scan shifted by [1e9, -1e9, 1e9]", offset=[1e9, -1e9, 1e9])
units(
    "offset-utm-f32",
    "UTM-like offset stored as float32 PLY (precision ~0.25, object 1.4)",
    offset=UTM,
    fmt="ply_f32",
    expect={0, 2, 3},
    twin=False,
    note="float32 cannot hold the data: any documented answer; a pose must not be wrong",
)


def _per_scan_offsets(ctx: Ctx):
    ctx.inp.mkdir()
    gt = ctx.gt()
    ctx.truth = {}
    rng = np.random.default_rng(5)
    for i in range(8):
        off = np.array(UTM) + rng.uniform(-1e4, 1e4, 3)
        name = ctx.write_scan(ctx.inp, i, "ply", offset=off)
        T = gt[f"scan_{i:03d}.ply"].copy()
        T[:3, 3] -= T[:3, :3] @ off
        ctx.truth[name] = T
    ctx.twin = ctx.fx["clean_registered"]


add(
    "offset-per-scan",
    "units",
    "each scan its own UTM-like offset (+-1e4), far apart",
    _per_scan_offsets,
    REG,
    {0},
    expect_result="full",
)

# ---------------------------------------------------------------- 3. ground truth


def gt_text(ctx: Ctx, kind: str) -> str:
    gt = {k: v.tolist() for k, v in ctx.gt().items()}
    d = {"format": "mvreg.poses/1", "poses": gt}
    k0 = "scan_000.ply"
    if kind == "valid":
        pass
    elif kind == "wrong-format":
        d["format"] = "mvreg.poses/99"
    elif kind == "no-format":
        del d["format"]
    elif kind == "no-poses":
        del d["poses"]
    elif kind == "poses-list":
        d["poses"] = list(gt.values())
    elif kind == "3x3":
        d["poses"][k0] = [r[:3] for r in gt[k0][:3]]
    elif kind == "3x4":
        d["poses"][k0] = gt[k0][:3]
    elif kind == "non-rigid":
        d["poses"][k0] = (np.diag([2.0, 1, 1, 1]) @ np.array(gt[k0])).tolist()
    elif kind == "reflection":
        d["poses"][k0] = (np.diag([-1.0, 1, 1, 1]) @ np.array(gt[k0])).tolist()
    elif kind == "nan":
        d["poses"][k0][0][3] = float("nan")
    elif kind == "inf":
        d["poses"][k0][1][3] = float("inf")
    elif kind == "strings":
        d["poses"][k0][0][0] = "one"
    elif kind == "bottom-row":
        d["poses"][k0][3] = [0, 0, 1, 1]
    elif kind == "dangling":
        d["poses"]["scan_999.ply"] = gt[k0]
    elif kind == "missing":
        d["poses"] = {k: v for k, v in gt.items() if k in ("scan_000.ply", "scan_001.ply")}
    elif kind == "empty-poses":
        d["poses"] = {}
    elif kind == "not-json":
        return "format: mvreg.poses/1\nposes: [1, 2\n"
    elif kind == "empty":
        return ""
    elif kind == "huge":
        eye = np.eye(4).tolist()
        d["poses"].update({f"ghost_{i:06d}.ply": eye for i in range(100_000)})
    elif kind == "top-list":
        return "[1, 2, 3]"
    else:
        raise ValueError(kind)
    return json.dumps(d)


GT_EVAL = [
    ("wrong-format", {2}, True),
    ("no-format", {2}, True),
    ("no-poses", {2}, True),
    ("poses-list", {2}, True),
    ("3x3", {2}, True),
    ("3x4", {2}, True),
    ("non-rigid", {2}, True),
    ("reflection", {2}, True),
    ("nan", {2}, True),
    ("inf", {2}, True),
    ("strings", {2}, True),
    ("bottom-row", {2}, True),
    ("not-json", {2}, True),
    ("empty", {2}, True),
    ("top-list", {2}, True),
    ("empty-poses", {2}, True),
    ("dangling", {0, 2}, False),
    ("missing", {0, 2}, False),
    ("huge", {0, 2}, False),
    ("valid", {0}, False),
]


def _gt_setup(kind):
    def setup(ctx: Ctx):
        ctx.inp.mkdir()
        (ctx.inp / "ground_truth.json").write_text(gt_text(ctx, kind))

    return setup


for kind, exp, must_name in GT_EVAL:
    add(
        f"eval-gt-{kind}",
        "ground-truth",
        f"mvreg eval, ground_truth.json: {kind}",
        _gt_setup(kind),
        ["eval", "{fx}/clean_result", "--truth", "{inp}/ground_truth.json"],
        set(exp),
        culprit=["ground_truth.json"] if must_name else ["ground_truth.json", "ghost", "scan_999"],
        expect_warn=["scan_999.ply"] if kind == "dangling" else [],
        note="a truth entry for a scan the result does not have must be named, not dropped"
        if kind == "dangling"
        else "",
    )


def _eval_bad_result(ctx: Ctx):
    ctx.inp.mkdir()
    shutil.copytree(ctx.froot / "clean_result", ctx.inp / "res")
    (ctx.inp / "res" / "poses.json").write_text('{"format": "mvreg.poses/1", "poses": {"a": ')
    shutil.copy(ctx.froot / "scans8" / "ground_truth.json", ctx.inp / "gt.json")


add(
    "eval-corrupt-poses",
    "ground-truth",
    "mvreg eval of a result whose poses.json is cut",
    _eval_bad_result,
    ["eval", "{inp}/res", "--truth", "{inp}/gt.json"],
    {2},
    culprit=["poses.json"],
)
add(
    "eval-missing-result",
    "ground-truth",
    "mvreg eval of a folder that does not exist",
    lambda c: (
        c.inp.mkdir(),
        shutil.copy(c.froot / "scans8" / "ground_truth.json", c.inp / "gt.json"),
    ),
    ["eval", "{work}/nope", "--truth", "{inp}/gt.json"],
    {2},
    culprit=["nope"],
)
add(
    "eval-truth-missing",
    "ground-truth",
    "mvreg eval --truth of a file that does not exist",
    None,
    ["eval", "{fx}/clean_result", "--truth", "{work}/nope.json"],
    {2},
    culprit=["nope.json"],
)
add(
    "eval-truth-dir",
    "ground-truth",
    "mvreg eval --truth a directory",
    lambda c: c.inp.mkdir(),
    ["eval", "{fx}/clean_result", "--truth", "{inp}"],
    {2},
    culprit=["in"],
)
add(
    "eval-poses-file",
    "ground-truth",
    "mvreg eval given poses.json itself",
    None,
    ["eval", "{fx}/clean_result/poses.json", "--truth", "{fx}/scans8/ground_truth.json"],
    {0},
)


def _eval_no_overlap(ctx: Ctx):
    ctx.inp.mkdir()
    d = {
        "format": "mvreg.poses/1",
        "poses": {f"other_{i}.ply": np.eye(4).tolist() for i in range(4)},
    }
    (ctx.inp / "gt.json").write_text(json.dumps(d))


add(
    "eval-no-common",
    "ground-truth",
    "mvreg eval with a truth sharing no scan name",
    _eval_no_overlap,
    ["eval", "{fx}/clean_result", "--truth", "{inp}/gt.json"],
    {2},
    culprit=["gt.json", "other_", "no scan", "common"],
)

# register with a ground_truth.json in the folder (used only for the report)
for kind, exp, warn in [
    ("nan", {0, 2}, ["ground_truth.json"]),
    ("dangling", {0, 2}, ["scan_999.ply"]),
    ("missing", {0}, []),
    ("not-json", {0, 2}, ["ground_truth.json"]),
    ("3x3", {0, 2}, ["ground_truth.json"]),
    ("wrong-format", {0, 2}, ["ground_truth.json"]),
    ("non-rigid", {0, 2}, ["ground_truth.json"]),
]:

    def _reg_gt(ctx: Ctx, kind=kind):
        ctx.scans()
        (ctx.inp / "ground_truth.json").write_text(gt_text(ctx, kind))

    add(
        f"register-gt-{kind}",
        "ground-truth",
        f"register with a ground_truth.json ({kind}) in the folder",
        _reg_gt,
        REG,
        exp,
        culprit=["ground_truth.json", "scan_999.ply"],
        expect_warn=warn,
        expect_result="full",
        note="README: every pose of ground_truth.json is checked; a bad one must be an error or "
        "a warning naming it, not silently ignored",
    )

# ---------------------------------------------------------------- 7. sequences

SEQ = ["register", "{inp}", "--out", "{out}", "--sequence"]


def seq_setup(frames=range(30), ts: str | None = "keep", rename=None):
    def setup(ctx: Ctx):
        ctx.inp.mkdir()
        src = ctx.froot / "seq30"
        gt = json.loads((src / "ground_truth.json").read_text())["poses"]
        ctx.truth = {}
        times = (src / "timestamps.txt").read_text().split()
        out_ts = []
        for k, i in enumerate(frames):
            name = f"scan_{i:03d}.ply" if rename is None else rename(k, i)
            shutil.copyfile(src / f"scan_{i:03d}.ply", ctx.inp / name)
            ctx.truth[name] = np.array(gt[f"scan_{i:03d}.ply"])
            out_ts.append(times[i])
        if ts == "keep":
            (ctx.inp / "timestamps.txt").write_text("\n".join(out_ts) + "\n")
        elif ts is not None:
            (ctx.inp / "timestamps.txt").write_text(ts)

    return setup


add("seq-valid", "sequence", "30-frame LiDAR sequence", seq_setup(), SEQ, {0}, expect_result="full")
_sh = [f"{t / 10:.1f}" for t in np.random.default_rng(7).permutation(30)]
add(
    "seq-shuffled-ts",
    "sequence",
    "timestamps.txt shuffled (not increasing in file order)",
    seq_setup(ts="\n".join(_sh) + "\n"),
    SEQ,
    {0, 2, 3},
    culprit=["timestamps.txt"],
    expect_warn=["timestamps"],
    note="non-monotonic timestamps: refuse or warn, never silently",
)
add(
    "seq-2-frames",
    "sequence",
    "a sequence of 2 frames",
    seq_setup(range(2)),
    SEQ,
    {0, 3},
    note="2 frames is the documented minimum",
)
add(
    "seq-1-frame",
    "sequence",
    "a sequence of 1 frame",
    seq_setup(range(1)),
    SEQ,
    {2},
    culprit=["in", "2", "scan"],
)
add(
    "seq-dup-frame",
    "sequence",
    "frame 10 present twice (scan_010.ply and scan_010b.ply)",
    seq_setup(
        [*range(11), 10, *range(11, 30)],
        rename=lambda k, i: "scan_010b.ply" if k == 11 else f"scan_{i:03d}.ply",
    ),
    SEQ,
    {0, 2, 3},
    culprit=["scan_010"],
    note="timestamps then repeat: refuse or register both at one pose",
)
add(
    "seq-gap",
    "sequence",
    "frames 10-17 missing (a gap)",
    seq_setup([*range(10), *range(18, 30)]),
    SEQ,
    {0, 3},
)
add(
    "seq-ts-garbage",
    "sequence",
    "timestamps.txt with a word in line 5",
    seq_setup(
        ts="\n".join(["0.0", "0.1", "0.2", "0.3", "abc"] + [f"{i / 10:.1f}" for i in range(5, 30)])
    ),
    SEQ,
    {0, 2},
    culprit=["timestamps.txt"],
    expect_warn=["timestamps.txt"],
)
add(
    "seq-ts-short",
    "sequence",
    "timestamps.txt with 10 lines for 30 frames",
    seq_setup(ts="\n".join(f"{i / 10:.1f}" for i in range(10))),
    SEQ,
    {0, 2},
    culprit=["timestamps.txt"],
    expect_warn=["timestamps.txt"],
)
add(
    "seq-ts-nan",
    "sequence",
    "timestamps.txt with nan in line 3",
    seq_setup(ts="\n".join(["0.0", "0.1", "nan"] + [f"{i / 10:.1f}" for i in range(3, 30)])),
    SEQ,
    {0, 2},
    culprit=["timestamps.txt"],
    expect_warn=["timestamps.txt"],
)
add(
    "seq-no-ts",
    "sequence",
    "no timestamps.txt (times from the names)",
    seq_setup(ts=None),
    SEQ,
    {0},
    expect_result="full",
)
add(
    "seq-reversed",
    "sequence",
    "frames named so the natural order is reversed",
    seq_setup(range(29, -1, -1), ts=None, rename=lambda k, i: f"f_{k:03d}.ply"),
    SEQ,
    {0, 3},
)


def _bin_setup(corrupt: str | None):
    def setup(ctx: Ctx):
        ctx.inp.mkdir()
        src = ctx.froot / "seq30"
        from bench.bad_input import read_ply_xyz

        for i in range(30):
            p = read_ply_xyz(src / f"scan_{i:03d}.ply").astype(np.float32)
            a = np.hstack([p, np.ones((len(p), 1), np.float32)])
            b = a.tobytes()
            if corrupt == "truncated" and i == 12:
                b = b[:-7]
            if corrupt == "empty" and i == 12:
                b = b""
            if corrupt == "nan" and i == 12:
                a[5, :3] = np.nan
                b = a.tobytes()
            (ctx.inp / f"{i:06d}.bin").write_bytes(b)

    return setup


BIN = ["register", "{inp}", "--out", "{out}", "--sequence", "--set", "sequence.dataloader=generic"]
add(
    "seq-kitti-bin",
    "sequence",
    "KITTI .bin folder (generic dataloader)",
    _bin_setup(None),
    BIN,
    {0, 3},
)
add(
    "seq-kitti-bin-truncated",
    "sequence",
    "KITTI .bin folder, 000012.bin not a multiple of 16 bytes",
    _bin_setup("truncated"),
    BIN,
    {2},
    culprit=["000012.bin"],
)
add(
    "seq-kitti-bin-empty",
    "sequence",
    "KITTI .bin folder, 000012.bin empty",
    _bin_setup("empty"),
    BIN,
    {2, 3},
    culprit=["000012.bin"],
)
add(
    "seq-kitti-bin-nan",
    "sequence",
    "KITTI .bin folder, a NaN point in 000012.bin",
    _bin_setup("nan"),
    BIN,
    {0, 2, 3},
    culprit=["000012.bin"],
    expect_warn=["000012.bin"],
)
add(
    "seq-dataloader-nonsense",
    "sequence",
    "--set sequence.dataloader=nonsense",
    seq_setup(),
    [*SEQ, "--set", "sequence.dataloader=nonsense"],
    {2},
    culprit=["dataloader", "nonsense"],
)
add(
    "seq-dataloader-kitti-bad",
    "sequence",
    "--set sequence.dataloader=kitti on a plain folder",
    seq_setup(),
    [*SEQ, "--set", "sequence.dataloader=kitti"],
    {2},
    culprit=["kitti", "dataloader", "in"],
)
add(
    "seq-max-frames-0",
    "sequence",
    "--set sequence.dataloader_max_frames=0 (generic)",
    _bin_setup(None),
    [*BIN, "--set", "sequence.dataloader_max_frames=0"],
    {2},
    culprit=["dataloader_max_frames", "max_frames"],
)
