"""Hostile-input corpus, families 5-6: outputs and faults (signals).
The cases are added to bad_input_cases_opts.CASES."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess

from bench.bad_input import (
    Ctx,
)
from bench.bad_input_cases_opts import (  # noqa: F401
    CASES,
    REG,
    add,
    scans,
)

# ---------------------------------------------------------------- 5. outputs (register)


def _o(cid, desc, setup, argv, exp, culprit=(), result="any", note="", skip=None, check=None):
    add(
        cid,
        "outputs",
        desc,
        setup,
        argv,
        set(exp),
        culprit=list(culprit),
        expect_result=result,
        note=note,
        skip=skip,
        check=check,
    )


def _set_out(path_fn, prev=None, make=None):
    def setup(ctx: Ctx):
        ctx.scans()
        ctx.out = path_fn(ctx)
        if prev:
            ctx.plant_prev(prev)
        if make:
            make(ctx)

    return setup


_o(
    "out-is-input",
    "register --out the input folder",
    _set_out(lambda c: c.inp),
    ["register", "{inp}", "--out", "{inp}"],
    {2},
    ["in", "--out", "input"],
)
_o(
    "out-is-input-force",
    "register --out the input folder --force",
    _set_out(lambda c: c.inp),
    ["register", "{inp}", "--out", "{inp}", "--force"],
    {2},
    ["in", "--out", "input"],
)
_o(
    "out-inside-input",
    "register --out inside the input folder",
    _set_out(lambda c: c.inp / "res"),
    ["register", "{inp}", "--out", "{inp}/res"],
    {2},
    ["res", "inside", "input"],
)
_o(
    "out-inside-input-dotdot",
    "register --out in/../in/res",
    _set_out(lambda c: c.inp / "res"),
    ["register", "{inp}", "--out", "{inp}/../in/res"],
    {2},
    ["res", "inside", "input"],
)


def _link_to_input(ctx):
    os.symlink(ctx.inp, ctx.work / "link")


_o(
    "out-symlink-to-input",
    "register --out a symlink to the input folder",
    _set_out(lambda c: c.work / "link", make=_link_to_input),
    ["register", "{inp}", "--out", "{work}/link", "--force"],
    {2},
    ["link", "input", "in"],
)
_o(
    "out-empty-string",
    "register --out ''",
    scans,
    ["register", "{inp}", "--out", ""],
    {2},
    ["--out", "empty"],
)
_o(
    "out-dot",
    "register --out . (the folder holding the input)",
    _set_out(lambda c: c.work),
    ["register", "{inp}", "--out", "."],
    {2},
    [".", "input", "contains", "files"],
)
_o(
    "out-root",
    "register --out /",
    _set_out(lambda c: c.work / "never"),
    ["register", "{inp}", "--out", "/"],
    {2},
    ["/"],
)


def _file(ctx):
    ctx.out.write_text("a file")
    ctx.prev = True


_o(
    "out-existing-file",
    "register --out an existing file",
    _set_out(lambda c: c.work / "out", make=_file),
    REG,
    {2},
    ["out"],
)
_o(
    "out-existing-file-force",
    "register --out an existing file --force",
    _set_out(lambda c: c.work / "out", make=_file),
    [*REG, "--force"],
    {2},
    ["out"],
)
_o(
    "out-prev-noforce",
    "register --out a folder with previous results, no --force",
    _set_out(lambda c: c.work / "out", prev="clean_result"),
    REG,
    {2},
    ["out", "--force"],
)
_o(
    "out-prev-force",
    "register --out previous results --force: fully replaced",
    _set_out(lambda c: c.work / "out", prev="clean_result"),
    [*REG, "--force"],
    {0},
    result="full",
)
_o(
    "out-prev-force-no-rrd",
    "previous results (with recording.rrd), --force --no-rrd: the old recording must not survive",
    _set_out(lambda c: c.work / "out", prev="clean_result"),
    [*REG, "--force", "--no-rrd"],
    {0},
    result="full",
)
_o(
    "out-prev-laz-noforce",
    "previous results of `--set output.merged_format=laz`, no --force",
    _set_out(lambda c: c.work / "out", prev="prev_laz"),
    REG,
    {2},
    ["out", "--force"],
)
_o(
    "out-prev-laz-force",
    "previous results of `--set output.merged_format=laz` (merged.laz), "
    "--force: mvreg wrote merged.laz itself, so it must be replaced",
    _set_out(lambda c: c.work / "out", prev="prev_laz"),
    [*REG, "--force"],
    {0},
    result="full",
)


def _foreign(ctx):
    ctx.out.mkdir()
    (ctx.out / "thesis.docx").write_text("precious")
    ctx.prev = True


_o(
    "out-foreign",
    "register --out a folder holding a foreign file",
    _set_out(lambda c: c.work / "out", make=_foreign),
    REG,
    {2},
    ["thesis.docx", "out"],
)
_o(
    "out-foreign-force",
    "register --out a folder holding a foreign file, --force",
    _set_out(lambda c: c.work / "out", make=_foreign),
    [*REG, "--force"],
    {2},
    ["thesis.docx", "out"],
)


def _prev_plus_foreign(ctx):
    (ctx.out / "notes.txt").write_text("mine")


_o(
    "out-prev-plus-foreign-force",
    "previous results plus a user's notes.txt, --force",
    _set_out(lambda c: c.work / "out", prev="clean_result", make=_prev_plus_foreign),
    [*REG, "--force"],
    {2},
    ["notes.txt"],
)
_o(
    "out-empty-dir",
    "register --out an existing empty folder",
    _set_out(lambda c: c.work / "out", make=lambda c: c.out.mkdir()),
    REG,
    {0},
    result="full",
)
_o(
    "out-trailing-slash",
    "register --out out/ (trailing slash)",
    _set_out(lambda c: c.work / "out"),
    ["register", "{inp}/", "--out", "{out}/"],
    {0},
    result="full",
)


def _ro_parent(ctx):
    (ctx.work / "ro").mkdir()
    os.chmod(ctx.work / "ro", 0o555)


_o(
    "out-ro-parent",
    "register --out inside a read-only folder",
    _set_out(lambda c: c.work / "ro" / "out", make=_ro_parent),
    ["register", "{inp}", "--out", "{work}/ro/out"],
    {2, 4},
    ["ro/out", "ro"],
    skip=lambda c: (
        "running as root: a 0555 folder is still writable" if os.geteuid() == 0 else None
    ),
)
_o(
    "out-proc",
    "register --out /proc/mvreg_out",
    _set_out(lambda c: c.work / "never"),
    ["register", "{inp}", "--out", "/proc/mvreg_out"],
    {2, 4},
    ["/proc/mvreg_out"],
    note="an unwritable place: 2 or 4, named; no leftovers",
)
_o(
    "out-dev-null",
    "register --out /dev/null",
    _set_out(lambda c: c.work / "never"),
    ["register", "{inp}", "--out", "/dev/null"],
    {2},
    ["/dev/null"],
)
_o(
    "out-deep-parent",
    "register --out a/b/c/out (parents missing)",
    _set_out(lambda c: c.work / "a" / "b" / "c" / "out"),
    ["register", "{inp}", "--out", "{work}/a/b/c/out"],
    {0, 2},
    ["a/b/c"],
)


def _dangling_out(ctx):
    os.symlink(ctx.work / "nowhere", ctx.work / "out")


_o(
    "out-dangling-symlink",
    "register --out a dangling symlink",
    _set_out(lambda c: c.work / "out", make=_dangling_out),
    REG,
    {0, 2},
    ["out"],
)


def _prev_clean(ctx):
    pass


_o(
    "rrd-input-scan",
    "register --rrd the input scan_000.ply",
    scans,
    [*REG, "--rrd", "{inp}/scan_000.ply"],
    {2},
    ["scan_000.ply", "--rrd"],
)
_o(
    "rrd-input-scan-force",
    "register --rrd the input scan_000.ply --force",
    scans,
    [*REG, "--rrd", "{inp}/scan_000.ply", "--force"],
    {2},
    ["scan_000.ply", "--rrd"],
)
_o(
    "rrd-in-input-folder",
    "register --rrd a new file inside the input folder",
    scans,
    [*REG, "--rrd", "{inp}/rec.rrd"],
    {2},
    ["rec.rrd", "input"],
    note="writing into the input folder would change the input; refuse like --out inside input",
)
_o(
    "rrd-proc",
    "register --rrd /proc/mvreg.rrd",
    scans,
    [*REG, "--rrd", "/proc/mvreg.rrd"],
    {2, 4},
    ["/proc/mvreg.rrd"],
    note="the recording cannot be written: named, no result half-kept",
)


def _old_rrd(ctx):
    ctx.scans()
    (ctx.work / "old.rrd").write_bytes(b"previous recording")
    ctx.inputs.append(ctx.work / "old.rrd")


_o(
    "rrd-existing-noforce",
    "register --rrd an existing file, no --force",
    _old_rrd,
    [*REG, "--rrd", "{work}/old.rrd"],
    {2},
    ["old.rrd"],
    note="old.rrd is hashed as an input: it must survive without --force",
)
_o("rrd-dir", "register --rrd a directory", scans, [*REG, "--rrd", "{work}"], {2}, ["--rrd", "rrd"])
_o(
    "rrd-no-parent",
    "register --rrd x/y/r.rrd (parents missing)",
    scans,
    [*REG, "--rrd", "{work}/x/y/r.rrd"],
    {0, 2},
    ["x/y"],
)
_o(
    "rrd-is-out-file",
    "register --rrd OUT/poses.json",
    scans,
    [*REG, "--rrd", "{out}/poses.json"],
    {2},
    ["poses.json", "--rrd"],
)


def _can_mount() -> bool:
    if os.geteuid() != 0:
        return False
    d = "/tmp/.mvreg_corpus_mount_probe"
    os.makedirs(d, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", d], capture_output=True)
    if r.returncode == 0:
        subprocess.run(["umount", d], capture_output=True)
        os.rmdir(d)
        return True
    return False


def _tiny(size, prev=False, where="out"):
    def setup(ctx: Ctx):
        ctx.scans()
        m = ctx.work / "tiny"
        m.mkdir()
        subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(m)], check=True)
        ctx.cleanup.insert(0, lambda: subprocess.run(["umount", "-l", str(m)], capture_output=True))
        if where == "out":
            ctx.out = m / "out"
            if prev:
                shutil.copytree(ctx.froot / "clean_result", ctx.out)
                ctx.prev = True

    return setup


def _skip_mount(c):
    return None if _can_mount() else "cannot mount a tmpfs here (not root or no CAP_SYS_ADMIN)"


_o(
    "out-full-disk",
    "register --out on a 64 KiB tmpfs (disk full)",
    _tiny("64k"),
    ["register", "{inp}", "--out", "{work}/tiny/out"],
    {4},
    ["tiny/out", "No space"],
    skip=_skip_mount,
    note="README: disk full -> exit 4 naming the file",
)
_o(
    "out-full-disk-prev",
    "previous results on a 2 MiB tmpfs, --force needs room for a second set",
    _tiny("2m", prev=True),
    ["register", "{inp}", "--out", "{work}/tiny/out", "--force"],
    {0, 4},
    ["tiny/out", "No space"],
    skip=_skip_mount,
    note="either fits or exit 4 naming the file with the previous set intact",
)
_o(
    "rrd-full-disk",
    "register --rrd on a 64 KiB tmpfs",
    _tiny("64k", where="rrd"),
    [*REG, "--rrd", "{work}/tiny/rec.rrd"],
    {4},
    ["rec.rrd", "No space"],
    skip=_skip_mount,
    check=lambda c, r: (
        [("BAD", "leftover on the full tmpfs: " + str(os.listdir(c.work / "tiny")))]
        if r.rc != 0 and os.path.isdir(c.work / "tiny") and os.listdir(c.work / "tiny")
        else []
    ),
)

# ---------------------------------------------------------------- 6. faults (signals)


def _fault(cid, desc, sig, delay, prev=True, followup=False, argv=None, setup=None, exp=None):
    def default_setup(ctx: Ctx):
        ctx.scans()
        if prev:
            ctx.plant_prev("clean_result")

    code = {signal.SIGINT: 130, signal.SIGTERM: 143, signal.SIGKILL: -9}[sig]
    a = argv or ([*REG, "--force"] if prev else REG)
    add(
        cid,
        "faults",
        desc,
        setup or default_setup,
        a,
        exp or {code, 0, 3},
        signal=(sig, delay),
        followup=followup,
        note="a run that finished before the signal is fine; otherwise "
        "the previous complete set (or nothing) must remain, no temp leftovers",
    )


for d in (0.3, 1.5, 3.0, 4.5):
    _fault(
        f"sigint-prev-{d}s",
        f"SIGINT {d} s into register --force over previous results",
        signal.SIGINT,
        d,
    )
for d in (1.0, 3.5):
    _fault(
        f"sigterm-prev-{d}s",
        f"SIGTERM {d} s into register --force over previous results",
        signal.SIGTERM,
        d,
    )
_fault(
    "sigint-fresh-2.5s",
    "SIGINT 2.5 s into register (no previous result)",
    signal.SIGINT,
    2.5,
    prev=False,
)
_fault(
    "sigterm-fresh-4s",
    "SIGTERM 4 s into register (no previous result)",
    signal.SIGTERM,
    4.0,
    prev=False,
)
for d in (1.5, 3.5, 5.0):
    _fault(
        f"sigkill-prev-{d}s",
        f"SIGKILL {d} s into register --force over previous results",
        signal.SIGKILL,
        d,
        followup=True,
    )
_fault(
    "sigkill-fresh-3s",
    "SIGKILL 3 s into register (no previous result)",
    signal.SIGKILL,
    3.0,
    prev=False,
    followup=True,
)
_fault(
    "sigint-synth-1s",
    "SIGINT 1 s into synth (30 views x 20000 points)",
    signal.SIGINT,
    1.0,
    prev=False,
    setup=lambda c: None,
    argv=["synth", "builtin", "--out", "{out}", "--views", "30", "--points-per-scan", "20000"],
)
_fault(
    "sigterm-mp-1s",
    "SIGTERM 1 s into make-problem --patches 3000",
    signal.SIGTERM,
    1.0,
    prev=False,
    setup=lambda c: setattr(c, "out", c.work / "p.npz"),
    argv=["make-problem", "--patches", "3000", "--out", "{work}/p.npz"],
)
_fault(
    "sigint-seq-2s",
    "SIGINT 2 s into register --sequence",
    signal.SIGINT,
    2.0,
    prev=False,
    setup=lambda c: (shutil.copytree(c.froot / "seq30", c.inp), None)[1],
    argv=["register", "{inp}", "--out", "{out}", "--sequence"],
)
