"""Run the hostile-input corpus against the real ``mvreg`` command line and grade it.

    PYTHONPATH=. .venv/bin/python scripts/bad_input_corpus.py [--jobs N] [--only ID ...]
        [--keep] [--out docs/benchmarks]

Writes OUT/bad_input.md and OUT/bad_input.json (with --only: no report unless --out is
given, so a partial run never replaces the full report; the verdicts are printed). Cases: bench/bad_input_cases*.py; harness
and grading rules: bench/bad_input.py.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import datetime
import json
import multiprocessing as mp
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench import bad_input as H  # noqa: E402
from bench import (  # noqa: E402
    bad_input_cases_more,
    bad_input_cases_opts,
    bad_input_cases_outputs,  # noqa: F401  (adds to bad_input_cases_opts.CASES)
    bad_input_cases_scans,
    bad_input_cases_scans2,  # noqa: F401  (adds to bad_input_cases_scans.CASES)
    bad_input_cases_solve,  # noqa: F401  (adds to bad_input_cases_opts.CASES)
)

ALL = bad_input_cases_scans.CASES + bad_input_cases_more.CASES + bad_input_cases_opts.CASES
BY_ID = {c.id: c for c in ALL}
_FX: dict = {}
_TMP: Path | None = None
_KEEP = False


def _run_one(cid: str) -> dict:
    return H.run_case(BY_ID[cid], _FX, _TMP, keep=_KEEP)


def machine() -> dict:
    mem = ""
    try:
        for ln in open("/proc/meminfo"):
            if ln.startswith("MemTotal"):
                mem = f"{int(ln.split()[1]) / 1024**2:.1f} GiB"
    except OSError:
        pass

    def sh(*a):
        try:
            return subprocess.run(a, capture_output=True, text=True, cwd=REPO).stdout.strip()
        except OSError:
            return ""

    return {
        "uname": " ".join(platform.uname()),
        "nproc": os.cpu_count(),
        "ram": mem,
        "commit": sh("git", "rev-parse", "HEAD"),
        "dirty": bool(sh("git", "status", "--porcelain", "--untracked-files=no")),
        "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "user": "root" if os.geteuid() == 0 else str(os.geteuid()),
    }


def cell(s: str) -> str:
    return str(s).replace("|", "\\|").replace("\n", " ")


def write_report(out_dir: Path, stem: str, recs: list[dict], meta: dict) -> None:
    counts = {v: sum(r["verdict"] == v for r in recs) for v in ("GOOD", "POOR", "BAD")}
    meta = {**meta, "counts": counts, "cases": len(recs)}
    (out_dir / f"{stem}.json").write_text(
        json.dumps({"meta": meta, "cases": recs}, indent=1) + "\n"
    )
    fams: dict[str, dict[str, int]] = {}
    for r in recs:
        f = fams.setdefault(r["family"], {"GOOD": 0, "POOR": 0, "BAD": 0})
        f[r["verdict"]] += 1
    L = [
        "# Hostile-input corpus (`scripts/bad_input_corpus.py`)",
        "",
        f"**{len(recs)} cases: {counts['GOOD']} GOOD, {counts['POOR']} POOR, {counts['BAD']} BAD** "
        f"in {meta['wall_s']:.0f} s wall time.",
        "",
        f"- command: `{meta['command']}`",
        f"- machine: `{meta['uname']}`, nproc {meta['nproc']}, RAM {meta['ram']}, user {meta['user']}",
        f"- mvreg commit: `{meta['commit']}`" + (" (working tree dirty)" if meta["dirty"] else ""),
        f"- date: {meta['date']}",
        "- each case: the real `mvreg` CLI in a subprocess, its own temp folder, timeout "
        f"{H.TIMEOUT_S:.0f} s, `RLIMIT_AS` {H.MEM_LIMIT / 1024**3:.0f} GiB; base data: "
        "`mvreg synth builtin --views 8 --points-per-scan 3000 --random-frames --seed 1` "
        f"(clean twin: exit {meta['fixtures'].get('clean_exit')}, "
        f"{meta['fixtures'].get('clean_registered')} of 8 registered), mutated per case",
        "",
        "## Grading rules (applied by code to every case)",
        "",
        H.RULES,
        "Each case also declares its expected exit codes, the culprit its message must name, "
        "whether a full result is expected and which warnings must appear "
        "(`bench/bad_input_cases*.py`). Where the right behaviour is debatable the case's "
        "note says so and the expectation follows the README contract.",
        "",
        "## By family",
        "",
        "| family | cases | GOOD | POOR | BAD |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for f, c in fams.items():
        L.append(f"| {f} | {sum(c.values())} | {c['GOOD']} | {c['POOR']} | {c['BAD']} |")
    L += [
        "",
        "## Cases that are not GOOD",
        "",
        "| id | verdict | command | exit | s | reasons | first stderr line |",
        "| --- | --- | --- | ---: | ---: | --- | --- |",
    ]
    for r in recs:
        if r["verdict"] == "GOOD":
            continue
        first = next(
            (ln for ln in r["stderr_head"] if "mvreg" in ln or "Error" in ln),
            (r["stderr_head"] or [""])[0],
        )
        L.append(
            f"| {r['id']} | {r['verdict']} | `{cell(r['command'])}` | {r['exit']} | "
            f"{r['seconds']} | {cell('; '.join(r['reasons']))} | {cell(first[:200])} |"
        )
    L += [
        "",
        "## All cases",
        "",
        "| id | family | input | exit | s | verdict | note |",
        "| --- | --- | --- | ---: | ---: | --- | --- |",
    ]
    for r in recs:
        extra = "; ".join(x for x in r["reasons"] if x != "ok")
        L.append(
            f"| {r['id']} | {r['family']} | {cell(r['desc'])} | {r['exit']} | {r['seconds']} | "
            f"{r['verdict']} | {cell(extra[:200])} |"
        )
    (out_dir / f"{stem}.md").write_text("\n".join(L) + "\n")


def main() -> int:
    global _FX, _TMP, _KEEP
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--only", nargs="+", default=None, metavar="ID")
    ap.add_argument("--keep", action="store_true", help="keep the temp folders of the cases")
    ap.add_argument(
        "--out",
        type=Path,
        default=None,
        help="report folder (default docs/benchmarks; with --only: no report unless given)",
    )
    ap.add_argument("--list", action="store_true", help="list the case ids and exit")
    args = ap.parse_args()
    dup = {c.id for c in ALL if sum(d.id == c.id for d in ALL) > 1}
    if dup:
        print(f"duplicate case ids: {sorted(dup)}", file=sys.stderr)
        return 2
    if args.list:
        for c in ALL:
            print(f"{c.id}\t{c.family}\t{c.desc}")
        return 0
    ids = [c.id for c in ALL]
    if args.only:
        unknown = [i for i in args.only if i not in BY_ID]
        if unknown:
            print(f"unknown case id(s): {unknown}", file=sys.stderr)
            return 2
        ids = args.only
    check = subprocess.run(
        [H.MVREG, "--version"], env=H.child_env(), capture_output=True, text=True
    )
    probe = subprocess.run(
        [sys.executable, "-c", "import mvreg; print(mvreg.__file__)"],
        env=H.child_env(),
        capture_output=True,
        text=True,
        cwd="/",
    )
    if not probe.stdout.strip().startswith(str(REPO)):
        print(f"mvreg resolves to {probe.stdout.strip()}, not this checkout", file=sys.stderr)
        return 2
    _TMP = Path(tempfile.mkdtemp(prefix="mvreg_bad_input_"))
    _KEEP = args.keep
    t0 = time.monotonic()
    print(f"fixtures in {_TMP} ...", flush=True)
    _FX = H.build_fixtures(_TMP / "_fixtures")
    print(
        f"fixtures ready ({time.monotonic() - t0:.0f} s; clean twin exit {_FX['clean_exit']}, "
        f"{_FX['clean_registered']} registered); {len(ids)} cases, {args.jobs} jobs",
        flush=True,
    )
    # long cases first for a balanced pool
    slow = ("faults", "units", "sequence")
    pos = {i: k for k, i in enumerate(ids)}
    ids = sorted(ids, key=lambda i: (BY_ID[i].family not in slow, pos[i]))
    recs: dict[str, dict] = {}
    ctx = mp.get_context("fork")
    with cf.ProcessPoolExecutor(max_workers=max(1, args.jobs), mp_context=ctx) as pool:
        futs = {pool.submit(_run_one, i): i for i in ids}
        for n, f in enumerate(cf.as_completed(futs), 1):
            i = futs[f]
            try:
                r = f.result()
            except Exception as e:  # a worker died: that is a harness failure, say so
                r = {
                    "id": i,
                    "family": BY_ID[i].family,
                    "desc": BY_ID[i].desc,
                    "note": "",
                    "command": "",
                    "exit": None,
                    "stderr_head": [],
                    "seconds": 0,
                    "verdict": "BAD",
                    "reasons": [f"HARNESS ERROR: {e!r}"],
                }
            recs[i] = r
            tail = f" kept in {r['kept']}" if r.get("kept") else ""
            print(
                f"[{n}/{len(ids)}] {r['verdict']:4} {i} (exit {r['exit']}, {r['seconds']} s)"
                + (f": {r['reasons'][0][:120]}" if r["verdict"] != "GOOD" else "")
                + tail,
                flush=True,
            )
    wall = time.monotonic() - t0
    order = [c.id for c in ALL if c.id in recs]
    meta = machine()
    cmd = "PYTHONPATH=. .venv/bin/python scripts/bad_input_corpus.py " + " ".join(sys.argv[1:])
    meta.update(
        command=cmd.strip(),
        wall_s=round(wall, 1),
        jobs=args.jobs,
        fixtures=_FX,
        mvreg_version=check.stdout.strip().splitlines()[:3],
    )
    stem = "bad_input"
    if args.out is None and not args.only:
        args.out = REPO / "docs" / "benchmarks"
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        write_report(args.out, stem, [recs[i] for i in order], meta)
    if args.only:
        for i in order:
            r = recs[i]
            print(f"{i}: {r['verdict']} exit {r['exit']} | {r['command']}")
            for x in r["reasons"]:
                print(f"    {x}")
            for x in r["stderr_head"][:3]:
                print(f"    stderr: {x[:200]}")
    if not args.keep:
        H._force_rmtree(_TMP)
    else:
        print(f"kept: {_TMP}")
    c = {v: sum(r["verdict"] == v for r in recs.values()) for v in ("GOOD", "POOR", "BAD")}
    print(
        f"{len(recs)} cases: {c['GOOD']} GOOD, {c['POOR']} POOR, {c['BAD']} BAD in {wall:.0f} s; "
        + (f"; wrote {args.out / (stem + '.md')}" if args.out else "")
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
