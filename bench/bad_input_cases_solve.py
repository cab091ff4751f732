"""Hostile-input corpus, family 8: patch problems (mvreg solve).
The cases are added to bad_input_cases_opts.CASES."""

from __future__ import annotations

import os
import shutil

import numpy as np

from bench.bad_input import (
    Ctx,
    npy_bytes,
)
from bench.bad_input_cases_opts import (  # noqa: F401
    CASES,
    REG,
    add,
    scans,
)

# ---------------------------------------------------------------- 8. patch problems: solve


def _load_problem(ctx: Ctx, which="problem.npz") -> dict:
    with np.load(ctx.froot / which, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def problem(mutate=None, which="problem.npz", raw: bytes | None = None):
    def setup(ctx: Ctx):
        ctx.inp.mkdir()
        ctx.out = ctx.work / "result.json"
        ctx.solve_truth = ctx.froot / which.replace(".npz", "_truth.json")
        if raw is not None:
            (ctx.inp / "p.npz").write_bytes(raw)
            return
        if mutate is None:
            shutil.copyfile(ctx.froot / which, ctx.inp / "p.npz")
            return
        arrs = mutate(_load_problem(ctx, which), ctx)
        if isinstance(arrs, bytes):
            (ctx.inp / "p.npz").write_bytes(arrs)
        else:
            np.savez(ctx.inp / "p.npz", **arrs)
            ctx.solve_truth = None if mutate is not _keep else ctx.solve_truth

    return setup


def _keep(a, ctx):
    return a


SOLVE = ["solve", "{inp}/p.npz", "--out", "{work}/result.json"]


def psolve(
    cid,
    desc,
    mutate=None,
    extra=(),
    exp=frozenset({2}),
    culprit=("p.npz",),
    note="",
    which="problem.npz",
    raw=None,
    check=None,
):
    add(
        cid,
        "patch-problems",
        desc,
        problem(mutate, which, raw),
        [*SOLVE, *extra],
        set(exp),
        culprit=list(culprit),
        note=note,
        check=check,
    )


for s in ["reg-admm", "spectral", "gpm", "balm", "c-admm"]:
    psolve(f"solve-{s}", f"solve --solver {s}", extra=["--solver", s], exp={0})
psolve("solve-2d", "solve a 2-D problem", which="problem2d.npz", exp={0})
psolve(
    "solve-solver-foo", "solve --solver foo", extra=["--solver", "foo"], culprit=["foo", "solver"]
)
for m, exp in [("dense", {0}), ("matrix-free", {0}), ("bogus", {2})]:
    psolve(
        f"solve-method-{m}",
        f"solve --method {m}",
        extra=["--method", m],
        exp=exp,
        culprit=["method", m],
    )
for r, exp in [
    ("-1", {2}),
    ("0", {2}),
    ("nan", {2}),
    ("inf", {2}),
    ("abc", {2}),
    ("1e300", {0, 2}),
    ("theorem4", {0}),
    ("balanced", {0}),
]:
    psolve(f"solve-rho-{r}", f"solve --rho {r}", extra=["--rho", r], exp=exp, culprit=["rho", r])
for v, exp in [("0", {0, 2}), ("-1", {2}), ("1000000000", {0})]:
    psolve(
        f"solve-max-iter-{v}",
        f"solve --max-iter {v}",
        extra=["--max-iter", v],
        exp=exp,
        culprit=["max-iter", "max_iter"],
    )
for v, exp in [("0", {0, 2}), ("-1", {2}), ("nan", {2}), ("inf", {2})]:
    psolve(f"solve-tol-{v}", f"solve --tol {v}", extra=["--tol", v], exp=exp, culprit=["tol"])
psolve("solve-seed-neg", "solve --seed -1", extra=["--seed", "-1"], exp={0, 2}, culprit=["seed"])
psolve(
    "solve-config-missing",
    "solve --config missing.json",
    extra=["--config", "{work}/missing.json"],
    culprit=["missing.json"],
)
psolve(
    "solve-set-bad",
    "solve --set solve.gpm.max_iter=-1",
    extra=["--set", "solve.gpm.max_iter=-1"],
    culprit=["max_iter"],
)
psolve(
    "solve-set-unknown",
    "solve --set solve.nosuch=1",
    extra=["--set", "solve.nosuch=1"],
    culprit=["nosuch"],
)
psolve("solve-reflections", "solve --allow-reflections", extra=["--allow-reflections"], exp={0})


def _out_setup(kind):
    base = problem()

    def setup(ctx: Ctx):
        base(ctx)
        if kind == "dir":
            ctx.out.mkdir()
        elif kind == "exists":
            ctx.out.write_text("{}")
            ctx.prev = True

    return setup


add(
    "solve-out-dir",
    "outputs",
    "solve --out an existing directory",
    _out_setup("dir"),
    SOLVE,
    {2},
    culprit=["result.json"],
)
add(
    "solve-out-exists",
    "outputs",
    "solve --out an existing file (no --force)",
    _out_setup("exists"),
    SOLVE,
    {2},
    culprit=["result.json", "--force"],
)
add(
    "solve-out-no-parent",
    "outputs",
    "solve --out in a folder that does not exist",
    problem(),
    ["solve", "{inp}/p.npz", "--out", "{work}/no/such/result.json"],
    {0, 2},
    culprit=["no/such"],
)
add(
    "solve-out-proc",
    "outputs",
    "solve --out /proc/mvreg_result.json",
    problem(),
    ["solve", "{inp}/p.npz", "--out", "/proc/mvreg_result.json"],
    {2, 4},
    culprit=["/proc/mvreg_result.json"],
)
add(
    "solve-out-is-input",
    "outputs",
    "solve --out the problem file itself",
    problem(),
    ["solve", "{inp}/p.npz", "--out", "{inp}/p.npz"],
    {2},
    culprit=["p.npz"],
)
add(
    "solve-out-is-input-force",
    "outputs",
    "solve --out the problem file itself, --force",
    problem(),
    ["solve", "{inp}/p.npz", "--out", "{inp}/p.npz", "--force"],
    {2},
    culprit=["p.npz"],
)

psolve("npz-not-zip", "problem: a text file named .npz", raw=b"coords patch node\n1 2 3\n")
psolve("npz-empty", "problem: zero-size .npz", raw=b"")
psolve(
    "npz-truncated",
    "problem: .npz cut in half",
    mutate=lambda a, c: (c.froot / "problem.npz").read_bytes()[:3000],
)
psolve("npz-npy", "problem: a .npy file named .npz", raw=npy_bytes(np.zeros((5, 3))))
for k in ("coords", "patch", "node"):
    psolve(
        f"npz-missing-{k}",
        f"problem without '{k}'",
        mutate=lambda a, c, k=k: {n: v for n, v in a.items() if n != k},
        culprit=[k],
    )


def _m(fn):
    def mutate(a, ctx):
        a = dict(a)
        fn(a)
        return a

    return mutate


MUT = [
    ("coords-1d", lambda a: a.update(coords=a["coords"][:, 0].copy()), {2}, ["coords"]),
    (
        "coords-4col",
        lambda a: a.update(coords=np.hstack([a["coords"], a["coords"][:, :1]])),
        {2},
        ["coords"],
    ),
    ("coords-1col", lambda a: a.update(coords=a["coords"][:, :1].copy()), {2}, ["coords"]),
    ("len-mismatch", lambda a: a.update(patch=a["patch"][:-5]), {2}, ["patch", "length"]),
    ("coords-nan", lambda a: a["coords"].__setitem__((3, 0), np.nan), {2}, ["coords", "nan"]),
    ("coords-inf", lambda a: a["coords"].__setitem__((3, 1), np.inf), {2}, ["coords", "inf"]),
    ("coords-1e200", lambda a: a.update(coords=a["coords"] * 1e200), {0, 2}, ["coords"]),
    ("coords-1e200-one", lambda a: a["coords"].__setitem__((3, 1), 1e200), {0, 2}, ["coords"]),
    (
        "coords-complex",
        lambda a: a.update(coords=a["coords"].astype(complex)),
        {2},
        ["coords", "complex"],
    ),
    ("coords-str", lambda a: a.update(coords=a["coords"].astype(str)), {2}, ["coords"]),
    (
        "coords-int",
        lambda a: a.update(coords=np.round(a["coords"] * 1000).astype(np.int64)),
        {0, 2},
        ["coords"],
    ),
    ("patch-1e9", lambda a: a["patch"].__setitem__(0, 10**9), {2}, ["patch", "1000000000"]),
    ("patch-neg", lambda a: a["patch"].__setitem__(0, -1), {2}, ["patch", "-1"]),
    ("patch-float", lambda a: a.update(patch=a["patch"] + 0.5), {2}, ["patch"]),
    (
        "patch-gap",
        lambda a: a.update(patch=np.where(a["patch"] > 5, a["patch"] + 1, a["patch"])),
        {2},
        ["patch", "6"],
    ),
    ("node-neg", lambda a: a["node"].__setitem__(0, -7), {2}, ["node", "-7"]),
    ("node-float", lambda a: a.update(node=a["node"] + 0.25), {2}, ["node"]),
    ("node-1e18", lambda a: a["node"].__setitem__(0, 10**18), {0, 2}, ["node"]),
    (
        "weight-neg",
        lambda a: a.update(weight=np.where(np.arange(len(a["patch"])) == 0, -1.0, 1.0)),
        {2},
        ["weight"],
    ),
    (
        "weight-nan",
        lambda a: a.update(weight=np.where(np.arange(len(a["patch"])) == 0, np.nan, 1.0)),
        {2},
        ["weight"],
    ),
    ("weight-zero", lambda a: a.update(weight=np.zeros(len(a["patch"]))), {2}, ["weight"]),
    ("weight-len", lambda a: a.update(weight=np.ones(3)), {2}, ["weight"]),
    ("names-len", lambda a: a.update(patch_names=np.array(["a", "b"])), {2}, ["patch_names"]),
    (
        "names-dup",
        lambda a: a.update(patch_names=np.array(["same"] * (a["patch"].max() + 1))),
        {2, 0},
        ["patch_names", "same"],
    ),
    (
        "node-twice",
        lambda a: (
            a["node"].__setitem__(1, a["node"][0])
            if a["patch"][1] == a["patch"][0]
            else a.update(
                node=np.concatenate([a["node"], a["node"][:1]]),
                patch=np.concatenate([a["patch"], a["patch"][:1]]),
                coords=np.vstack([a["coords"], a["coords"][:1] + 1]),
            )
        ),
        {2},
        ["node", "twice"],
    ),
    ("single-patch", lambda a: a.update(patch=np.zeros_like(a["patch"])), {2}, ["patch"]),
    (
        "no-observations",
        lambda a: a.update(coords=np.zeros((0, 3)), patch=np.zeros(0, int), node=np.zeros(0, int)),
        {2},
        ["p.npz", "empty", "observ"],
    ),
    ("extra-array", lambda a: a.update(junk=np.arange(3)), {0, 2}, ["junk"]),
    ("coords-f32", lambda a: a.update(coords=a["coords"].astype(np.float32)), {0}, []),
]
for mid, fn, exp, cul in MUT:
    psolve(f"npz-{mid}", f"problem: {mid}", mutate=_m(fn), exp=exp, culprit=cul or ["p.npz"])


def _disconnected(a, ctx):
    M = int(a["patch"].max()) + 1
    N = int(a["node"].max()) + 1
    return {
        "coords": np.vstack([a["coords"], a["coords"]]),
        "patch": np.concatenate([a["patch"], a["patch"] + M]),
        "node": np.concatenate([a["node"], a["node"] + N]),
    }


psolve(
    "npz-disconnected",
    "problem: two disconnected copies",
    mutate=_disconnected,
    culprit=["component", "disconnected", "connected"],
)


def _pickled_npz(a, ctx):
    import io
    import zipfile

    class Pwn:
        def __reduce__(self):
            return (os.system, ("touch PWNED_BY_PICKLE",))

    obj = np.empty(1, dtype=object)
    obj[0] = Pwn()
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for k, v in a.items():
            z.writestr(k + ".npy", npy_bytes(obj if k == "coords" else v))
    return buf.getvalue()


psolve(
    "npz-object-pickle",
    "problem: 'coords' is a pickled object array that runs a command",
    mutate=_pickled_npz,
    culprit=["coords", "p.npz"],
    check=lambda c, r: (
        [("BAD", "pickle in .npz was loaded: code ran")]
        if (c.work / "PWNED_BY_PICKLE").exists()
        else []
    ),
)
