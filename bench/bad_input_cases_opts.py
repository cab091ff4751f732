"""Hostile-input corpus, families 4-6 and 8: options, outputs, faults (signals), patch
problems (``mvreg solve`` / ``mvreg make-problem``)."""

from __future__ import annotations

import numpy as np

from bench.bad_input import Case, Ctx

REG = ["register", "{inp}", "--out", "{out}"]
CASES: list[Case] = []


def add(*a, **k) -> None:
    CASES.append(Case(*a, **k))


def scans(ctx: Ctx):
    ctx.scans()


# ---------------------------------------------------------------- 4. options: register
ABSURD = ["0", "-1", "nan", "inf", "-inf", "1e12", "1e-12", "abc", ""]
for v in ABSURD:
    exp = {2}
    note = ""
    if v == "1e-12":
        exp, note = {0, 2, 3}, "a tiny voxel is legal but absurd: refuse or cope"
    if v == "1e12":
        exp, note = (
            {2, 3},
            "a voxel larger than the object: refuse (absurd) or leave scans out, named",
        )
    add(
        f"opt-voxel-{v or 'empty'}",
        "options",
        f"register --voxel-size {v!r}",
        scans,
        [*REG, "--voxel-size", v],
        exp,
        culprit=["voxel"],
        note=note,
    )
add(
    "opt-voxel-valid",
    "options",
    "register --voxel-size 0.03",
    scans,
    [*REG, "--voxel-size", "0.03"],
    {0, 3},
)
for v, exp in [("-1", {2}), ("abc", {2}), ("0", {0}), ("1000000", {0, 2}), ("1.5", {2})]:
    add(
        f"opt-refine-{v}",
        "options",
        f"register --refine {v}",
        scans,
        [*REG, "--refine", v],
        exp,
        culprit=["refine"],
    )
for v, exp in [("-5", {0, 2}), ("18446744073709551621", {0, 2}), ("abc", {2}), ("1.5", {2})]:
    add(
        f"opt-seed-{v[:8]}",
        "options",
        f"register --seed {v}",
        scans,
        [*REG, "--seed", v],
        exp,
        culprit=["seed"],
    )
for v, exp in [("0", {2}), ("-1", {2}), ("100000", {0, 2}), ("abc", {2})]:
    add(
        f"opt-threads-{v}",
        "options",
        f"register --threads {v}",
        scans,
        [*REG, "--threads", v],
        exp,
        culprit=["threads"],
    )
for v, exp in [("0", {0, 2}), ("-1", {2}), ("abc", {2})]:
    add(
        f"opt-workers-{v}",
        "options",
        f"register --workers {v}",
        scans,
        [*REG, "--workers", v],
        exp,
        culprit=["workers"],
    )
add(
    "opt-workers-1",
    "options",
    "register --workers 1 (a local Dask cluster)",
    scans,
    [*REG, "--workers", "1"],
    {0},
    expect_result="full",
)
add(
    "opt-workers-and-scheduler",
    "options",
    "register --workers 2 --scheduler tcp://127.0.0.1:1",
    scans,
    [*REG, "--workers", "2", "--scheduler", "tcp://127.0.0.1:1"],
    {2},
    culprit=["--workers", "--scheduler", "workers", "scheduler"],
)
add(
    "opt-scheduler-garbage",
    "options",
    "register --scheduler 'not an address'",
    scans,
    [*REG, "--scheduler", "not an address"],
    {2},
    culprit=["scheduler", "not an address"],
)
add(
    "opt-scheduler-refused",
    "options",
    "register --scheduler tcp://127.0.0.1:1 (nothing listens)",
    scans,
    [*REG, "--scheduler", "tcp://127.0.0.1:1"],
    {2, 4},
    culprit=["127.0.0.1:1", "scheduler"],
    note="connection refused: an environment fault (4) or bad input (2), named",
)
for s in ["reg-admm", "spectral", "gpm", "balm", "c-admm"]:
    add(
        f"opt-solver-{s}",
        "options",
        f"register --solver {s}",
        scans,
        [*REG, "--solver", s],
        {0},
        expect_result="full",
    )
for s, exp in [("foo", {2}), ("", {2}), ("REG-ADMM", {0, 2})]:
    add(
        f"opt-solver-bad-{s or 'empty'}",
        "options",
        f"register --solver {s!r}",
        scans,
        [*REG, "--solver", s],
        exp,
        culprit=["solver", s or "solver"],
    )
add(
    "opt-rrd-and-no-rrd",
    "options",
    "register --rrd x.rrd --no-rrd",
    scans,
    [*REG, "--rrd", "{work}/x.rrd", "--no-rrd"],
    {0, 2},
    culprit=["--rrd", "--no-rrd"],
)

CFG = {
    "missing": None,
    "broken-json": '{"refine": {"rounds": 2}',
    "unknown-section": '{"nosuch": {"a": 1}}',
    "unknown-key": '{"refine": {"roundz": 2}}',
    "wrong-type": '{"refine": {"rounds": "many"}}',
    "negative": '{"preprocess": {"voxel_size": -1}}',
    "nan": '{"preprocess": {"voxel_size": NaN}}',
    "top-list": "[1, 2]",
    "empty": "",
    "section-scalar": '{"refine": 3}',
}
for k, text in CFG.items():

    def _cfg(ctx: Ctx, text=text):
        ctx.scans()
        if text is not None:
            (ctx.work / "cfg.json").write_text(text)
            ctx.inputs.append(ctx.work / "cfg.json")

    exp = {0, 2} if k == "empty" else {2}
    add(
        f"opt-config-{k}",
        "options",
        f"register --config cfg.json ({k})",
        _cfg,
        [*REG, "--config", "{work}/cfg.json"],
        exp,
        culprit=["cfg.json", "roundz", "nosuch", "rounds", "voxel_size", "refine"],
    )
add(
    "opt-config-dir",
    "options",
    "register --config a directory",
    scans,
    [*REG, "--config", "{inp}"],
    {2},
    culprit=["in", "config"],
)


def _yaml(ctx: Ctx):
    ctx.scans()
    (ctx.work / "cfg.yaml").write_text("refine:\n  rounds: [1, 2\n")
    ctx.inputs.append(ctx.work / "cfg.yaml")


add(
    "opt-config-yaml-broken",
    "options",
    "register --config broken YAML",
    _yaml,
    [*REG, "--config", "{work}/cfg.yaml"],
    {2},
    culprit=["cfg.yaml"],
)
SETS = [
    ("no-equals", "refine.rounds", {2}),
    ("unknown-field", "nosuch.field=1", {2}),
    ("bad-value", "refine.rounds=abc", {2}),
    ("seed-abc", "seed=abc", {2}),
    ("min-points-1e9", "min_points=1000000000", {2}),
    ("min-points-neg", "min_points=-1", {2}),
    ("min-points-0", "min_points=0", {0, 2}),
    ("min-points-2900", "min_points=2900", {2, 3}),
    ("merged-xyz", "output.merged_format=xyz", {2}),
    ("merged-laz", "output.merged_format=laz", {0}),
    ("merged-e57", "output.merged_format=e57", {0}),
    ("rounds-neg", "refine.rounds=-3", {2}),
    ("voxel-nan", "preprocess.voxel_size=NaN", {2}),
    ("empty-key", "=1", {2}),
    ("ransac-0", "align.ransac_max_iterations=0", {2}),
    ("ransac-1e12", "align.ransac_max_iterations=1000000000000", {2}),
    ("section-only", "pairs", {2}),
    ("solver-nope", "solve.solver=nope", {2}),
    ("threads-0", "threads=0", {2}),
    ("deep-unknown", "solve.gpm.nosuch=1", {2}),
]
for sid, val, exp in SETS:
    key = val.split("=")[0] or "="
    add(
        f"opt-set-{sid}",
        "options",
        f"register --set {val}",
        scans,
        [*REG, "--set", val],
        exp,
        culprit=[key, key.split(".")[-1], val],
    )

# ---------------------------------------------------------------- 4. options: synth
SYN = ["synth", "builtin", "--out", "{out}", "--views", "4", "--points-per-scan", "500"]


def _synth_ok(ctx: Ctx, run):
    if run.rc != 0:
        return []
    gt = ctx.out / "ground_truth.json"
    if not gt.is_file() or not list(ctx.out.glob("scan_*")):
        return [("BAD", "synth exit 0 without ground_truth.json and scans")]
    return []


SYN_OPTS = [
    ("views-0", ["--views", "0"], {2}),
    ("views-neg", ["--views", "-1"], {2}),
    ("views-1", ["--views", "1"], {0, 2}),
    ("views-1e6", ["--views", "1000000"], {2}),
    ("pps-0", ["--points-per-scan", "0"], {2}),
    ("pps-neg", ["--points-per-scan", "-1"], {2}),
    ("pps-1e12", ["--points-per-scan", "1000000000000"], {2}),
    ("noise-neg", ["--noise", "-1"], {2}),
    ("noise-nan", ["--noise", "nan"], {2}),
    ("noise-inf", ["--noise", "inf"], {2}),
    ("noise-1e12", ["--noise", "1e12"], {2}),
    ("outliers-neg", ["--outliers", "-0.1"], {2}),
    ("outliers-1.5", ["--outliers", "1.5"], {2}),
    ("outliers-nan", ["--outliers", "nan"], {2}),
    ("dropout-1", ["--dropout", "1.0"], {2}),
    ("dropout-2", ["--dropout", "2"], {2}),
    ("dropout-nan", ["--dropout", "nan"], {2}),
    ("distance-0", ["--distance", "0"], {2}),
    ("distance-neg", ["--distance", "-1"], {2}),
    ("distance-nan", ["--distance", "nan"], {2}),
    ("distance-1e-12", ["--distance", "1e-12"], {2}),
    ("distance-1e12", ["--distance", "1e12"], {2}),
    ("elevation-nan", ["--elevation", "nan"], {2}),
    ("elevation-1e12", ["--elevation", "1e12"], {0, 2}),
    ("rate-0", ["--sequence", "--rate-hz", "0"], {2}),
    ("rate-nan", ["--sequence", "--rate-hz", "nan"], {2}),
    ("placement-bogus", ["--placement", "bogus"], {2}),
    ("scanner-bogus", ["--scanner", "bogus"], {2}),
    ("seed-neg", ["--seed", "-1"], {0, 2}),
    ("seed-abc", ["--seed", "abc"], {2}),
]
for sid, extra, exp in SYN_OPTS:
    opt = extra[-2]
    add(
        f"synth-{sid}",
        "options",
        "synth " + " ".join(extra),
        None,
        [*SYN, *extra],
        exp,
        culprit=[opt, opt.lstrip("-"), extra[-1]],
        check=_synth_ok,
    )


def _vp(text):
    def setup(ctx: Ctx):
        ctx.inp.mkdir()
        if text is not None:
            (ctx.inp / "vp.txt").write_text(text)

    return setup


for sid, text, exp in [
    ("missing", None, {2}),
    ("empty", "", {2}),
    ("garbage", "a b c\n", {2}),
    ("nan", "nan 0 0\n1 1 1\n", {2}),
    ("one", "2 0 0\n", {0, 2}),
    ("centre", "0 0 0\n0 0 0\n", {2}),
    ("two-cols", "1 2\n3 4\n", {2}),
]:
    add(
        f"synth-viewpoints-{sid}",
        "options",
        f"synth --viewpoints ({sid})",
        _vp(text),
        [
            "synth",
            "builtin",
            "--out",
            "{out}",
            "--points-per-scan",
            "500",
            "--viewpoints",
            "{inp}/vp.txt",
        ],
        exp,
        culprit=["vp.txt", "viewpoint"],
        check=_synth_ok,
    )


def _mesh(kind):
    def setup(ctx: Ctx):
        ctx.inp.mkdir()
        p = ctx.inp / ("m.xyz" if kind == "xyz" else "m.obj")
        if kind == "garbage":
            p.write_bytes(np.random.default_rng(9).bytes(5000))
        elif kind == "empty":
            p.write_text("")
        elif kind == "degenerate":
            p.write_text("v 0 0 0\nv 0 0 0\nv 0 0 0\nf 1 2 3\n")
        elif kind == "xyz":
            p.write_text("0 0 0\n1 1 1\n")

    return setup


for kind in ["garbage", "empty", "degenerate", "xyz"]:
    name = "m.xyz" if kind == "xyz" else "m.obj"
    add(
        f"synth-mesh-{kind}",
        "options",
        f"synth of a mesh file ({kind})",
        _mesh(kind),
        ["synth", f"{{inp}}/{name}", "--out", "{out}", "--views", "4", "--points-per-scan", "500"],
        {2},
        culprit=[name],
        check=_synth_ok,
    )
add(
    "synth-mesh-missing",
    "options",
    "synth of a mesh that does not exist",
    None,
    ["synth", "{work}/nope.obj", "--out", "{out}", "--views", "4"],
    {2},
    culprit=["nope.obj"],
)
add(
    "synth-mesh-dir",
    "options",
    "synth of a directory",
    lambda c: c.inp.mkdir(),
    ["synth", "{inp}", "--out", "{out}", "--views", "4"],
    {2},
    culprit=["in"],
)
add(
    "synth-mesh-shared",
    "options",
    "synth of a real mesh (shared fandisk.obj)",
    None,
    [
        "synth",
        "/work/shared/data/meshes/fandisk.obj",
        "--out",
        "{out}",
        "--views",
        "4",
        "--points-per-scan",
        "500",
    ],
    {0},
    check=_synth_ok,
)
for b, exp in [("builtin:abc", {2}), ("builtin:-1", {0, 2}), ("builtin:", {0, 2})]:
    add(
        f"synth-{b.replace(':', '-')}",
        "options",
        f"synth {b}",
        None,
        ["synth", b, "--out", "{out}", "--views", "4", "--points-per-scan", "500"],
        exp,
        culprit=[b, "builtin"],
        check=_synth_ok,
    )


def _synth_prev(ctx: Ctx):
    ctx.out.mkdir()
    (ctx.out / "mine.txt").write_text("precious")
    ctx.prev = True


add(
    "synth-out-nonempty",
    "options",
    "synth --out a folder holding the user's file (no --force)",
    _synth_prev,
    SYN,
    {2},
    culprit=["out", "--force"],
)
add(
    "synth-out-nonempty-force",
    "options",
    "synth --out a folder holding the user's file, --force",
    _synth_prev,
    [*SYN, "--force"],
    {0, 2},
    culprit=["out", "mine.txt"],
    check=lambda c, r: (
        [("BAD", "synth --force deleted a file it did not write")]
        if not (c.out / "mine.txt").exists()
        else []
    ),
)


def _out_file(ctx: Ctx):
    ctx.out.write_text("a file")
    ctx.prev = True


add(
    "synth-out-file",
    "options",
    "synth --out an existing file",
    _out_file,
    SYN,
    {2},
    culprit=["out"],
)

# ---------------------------------------------------------------- 4. options: make-problem
MP = ["make-problem", "--out", "{work}/p.npz"]


def _mp_setup(ctx: Ctx):
    ctx.out = ctx.work / "p.npz"


MP_OPTS = [
    ("patches-0", ["--patches", "0"], {2}),
    ("patches-1", ["--patches", "1"], {2}),
    ("patches-neg", ["--patches", "-1"], {2}),
    ("patches-2", ["--patches", "2"], {0, 2}),
    ("patches-1e12", ["--patches", "1000000000000"], {2}),
    ("d-4", ["--d", "4"], {2}),
    ("d-1", ["--d", "1"], {2}),
    ("degree-0", ["--degree", "0"], {2}),
    ("degree-1e9", ["--degree", "1000000000"], {2}),
    ("nodes-0", ["--nodes-per-pair", "0"], {2}),
    ("nodes-1e9", ["--nodes-per-pair", "1000000000"], {2}),
    ("noise-neg", ["--noise", "-1"], {2}),
    ("noise-nan", ["--noise", "nan"], {2}),
    ("noise-inf", ["--noise", "inf"], {2}),
    ("outliers-2", ["--outliers", "2"], {2}),
    ("outliers-nan", ["--outliers", "nan"], {2}),
    ("seed-neg", ["--seed", "-1"], {0, 2}),
]
for sid, extra, exp in MP_OPTS:
    add(
        f"mp-{sid}",
        "options",
        "make-problem " + " ".join(extra),
        _mp_setup,
        [*MP, *extra],
        exp,
        culprit=[extra[0], extra[0].lstrip("-"), extra[1]],
    )


def _mp_exists(ctx: Ctx):
    ctx.out = ctx.work / "p.npz"
    ctx.out.write_bytes(b"mine")
    ctx.prev = True


add(
    "mp-out-exists",
    "options",
    "make-problem --out an existing file (no --force)",
    _mp_exists,
    MP,
    {2},
    culprit=["p.npz"],
)
add(
    "mp-out-exists-force",
    "options",
    "make-problem --out an existing file, --force",
    _mp_exists,
    [*MP, "--force"],
    {0},
)
add(
    "mp-out-dir",
    "options",
    "make-problem --out a directory",
    lambda c: (setattr(c, "out", c.work / "d.npz"), c.out.mkdir()),
    ["make-problem", "--out", "{work}/d.npz"],
    {2},
    culprit=["d.npz"],
)
add(
    "mp-out-no-parent",
    "options",
    "make-problem --out in a folder that does not exist",
    lambda c: setattr(c, "out", c.work / "no" / "p.npz"),
    ["make-problem", "--out", "{work}/no/p.npz"],
    {0, 2},
    culprit=["no/p.npz", "p.npz"],
)
