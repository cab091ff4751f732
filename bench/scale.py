"""Scale benchmark of `mvreg register` (issue 14): time, memory and accuracy against the
number of scans.

1. Builtin-object scans, ``mvreg synth builtin --views V --points-per-scan 10000 --seed 1``
   for V in 20, 40, 80, 160, 320 (``--sizes``), each registered with default settings.
2. A scene-like set (``--scene FRAMES``, 0: none): a LiDAR with a short range
   (``--scene-range`` m) driven once around a loop through data_synth's scene of objects
   and box buildings, so each scan overlaps only its neighbours along the path;
   registered as unordered scans (no ``--sequence``).

Each registration runs as its own ``python -m mvreg.cli register`` process: its wall
time, the stage times of its report.json, its peak resident memory (``ru_maxrss`` of
that process from ``os.wait4``), the largest rotation error against the ground truth and
the number of candidate and refinement pairs. The total and stage times are fitted
against the number of scans on a log-log scale (least squares; exponent 1: linear).
The data are synthesized once into ``--data`` and reused.

Writes docs/benchmarks/scale.md (the text after its notes marker is kept), scale.json and
scale.png; ``--rerender`` rewrites scale.md and the plot from scale.json.

    python scripts/bench_scale.py                      # 20 40 80 160 320 + scene of 60
    python scripts/bench_scale.py --sizes 20,40,80 --scene 0
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from bench.common import ROOT, machine

STAGES = ("preprocess", "pairwise", "tracks_and_solve", "robust", "refine", "verification")


def stage_times(timings: dict) -> dict:
    """The report's ``timings_s`` with ``verification``: the verification and the placing
    of leftovers (``verify_with_resolves`` also holds the re-runs of the global stage)."""
    out = dict(timings)
    out["verification"] = timings.get("verify", 0.0) + timings.get("place_leftovers", 0.0)
    return out


def synth_builtin(data: Path, views: int, points: int) -> Path:
    folder = data / f"builtin_{views}_{points}"
    if not (folder / "ground_truth.json").exists():
        cmd = ["synth", "builtin", "--views", str(views), "--points-per-scan", str(points)]
        _mvreg([*cmd, "--seed", "1", "--out", str(folder), "--force"])
    return folder


def synth_scene(data: Path, frames: int, range_m: float, points: int) -> Path:
    from data_synth import synthesize_sequence

    folder = data / f"scene_{frames}_{range_m:g}_{points}"
    if not (folder / "ground_truth.json").exists():
        synthesize_sequence(
            None, folder, frames=frames, points_per_scan=points, max_range_m=range_m, seed=0,
            force=True,
        )  # fmt: skip
        (folder / "timestamps.txt").unlink()  # registered as unordered scans
    return folder


def _mvreg(args: list[str]) -> subprocess.CompletedProcess:
    env = dict(os.environ, OPENBLAS_NUM_THREADS=os.environ.get("OPENBLAS_NUM_THREADS", "1"))
    return subprocess.run(
        [sys.executable, "-m", "mvreg.cli", *args], env=env, check=True, capture_output=True
    )


def register(folder: Path, out: Path, extra: list[str], rrd: bool = False) -> dict:
    """One `mvreg register` process (``--no-rrd`` unless ``rrd``): wall time, peak memory
    and its report's figures."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS=os.environ.get("OPENBLAS_NUM_THREADS", "1"))
    cmd = [sys.executable, "-m", "mvreg.cli", "register", str(folder), "--out", str(out)]
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        [*cmd, *([] if rrd else ["--no-rrd"]), "--force", *extra],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    code = os.waitstatus_to_exitcode(status)
    row = {"folder": folder.name, "exit": code, "wall": wall, "load_start": load}
    row["load_end"] = os.getloadavg()[0]
    row["peak_rss_mib"] = usage.ru_maxrss / 1024.0  # kilobytes on Linux
    report = out / "report.json"
    if code not in (0, 3) or not report.exists():
        row["error"] = proc.stderr.read().decode(errors="replace")[-2000:]
        return row
    rep = json.loads(report.read_text())
    e = rep.get("ground_truth_errors") or {}
    row.update(
        scans=len(rep["scans"]) if isinstance(rep["scans"], list) else rep["scans"],
        registered=len(rep["registered"]),
        timings=stage_times(rep["timings_s"]),
        rot_max=e.get("rotation_deg_max"),
        rot_median=e.get("rotation_deg_median"),
        candidate_pairs=len(rep["pairs"]),
        refine_pairs=[r["pairs"] for r in rep.get("refine_rounds") or []],
        joint_icp_pairs=(rep.get("joint_icp") or {}).get("pairs"),
    )
    return row


def fit_exponent(n, t) -> float | None:
    """Slope of log t against log n (least squares); None with fewer than two points."""
    n, t = np.asarray(n, float), np.asarray(t, float)
    ok = (n > 0) & (t > 0) & np.isfinite(t)
    if np.count_nonzero(ok) < 2:
        return None
    return float(np.polyfit(np.log(n[ok]), np.log(t[ok]), 1)[0])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--sizes", default="20,40,80,160,320", help="numbers of builtin scans")
    ap.add_argument("--points", type=int, default=10000, help="points per builtin scan")
    ap.add_argument("--scene", type=int, default=60, help="scene-like scans (0: none)")
    ap.add_argument("--scene-range", type=float, default=12.0, help="scene LiDAR range, m")
    ap.add_argument("--data", type=Path, default=Path("/tmp/mvreg_scale_data"))
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks")
    ap.add_argument("--rerender", action="store_true", help="rewrite scale.md from scale.json")
    a = ap.parse_args(argv)
    if a.rerender:
        saved = json.loads((a.out / "scale.json").read_text())
        for r in [*saved["rows"], *([saved["scene"]] if saved["scene"] else [])]:
            if "timings" in r:
                r["timings"] = stage_times(r["timings"])
        write_report(a, saved["rows"], saved["scene"])
        return
    a.data.mkdir(parents=True, exist_ok=True)
    rows = []
    for v in [int(x) for x in a.sizes.split(",") if x]:
        folder = synth_builtin(a.data, v, a.points)
        print(f"builtin {v} ...", file=sys.stderr, flush=True)
        rows.append({"set": "builtin", "views": v, **register(folder, a.data / "out", [])})
        print(_line(rows[-1]), file=sys.stderr, flush=True)
    scene = None
    if a.scene:
        folder = synth_scene(a.data, a.scene, a.scene_range, a.points)
        print(f"scene {a.scene} ...", file=sys.stderr, flush=True)
        scene = {"set": "scene", "views": a.scene, **register(folder, a.data / "out", [])}
        print(_line(scene), file=sys.stderr, flush=True)
    write_report(a, rows, scene)


def _line(r: dict) -> str:
    if "error" in r:
        return f"  exit {r['exit']}: {r['error'][-300:]}"
    return (
        f"  {r['wall']:.1f} s, peak {r['peak_rss_mib']:.0f} MiB, rot max {r['rot_max']} deg, "
        f"{r['registered']}/{r['scans']} registered, load {r['load_start']:.1f}"
    )


def _plot(rows, path: Path) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if "timings" in r]
    n = [r["views"] for r in ok]
    fits = {"total": fit_exponent(n, [r["timings"]["total"] for r in ok])}
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for key in ("total", *STAGES):
        t = [r["timings"].get(key, np.nan) for r in ok]
        fits[key] = fit_exponent(n, t)
        label = f"{key} (exponent {fits[key]:.2f})" if fits[key] is not None else key
        ax.loglog(
            n, t, "o-" if key == "total" else ".--", label=label, lw=2 if key == "total" else 1
        )
    ax.set_xlabel("scans (builtin object, 10k points each)")
    ax.set_ylabel("seconds")
    ax.set_title("mvreg register: time against scans")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return fits


def write_report(a, rows, scene) -> None:
    a.out.mkdir(parents=True, exist_ok=True)
    fits = _plot(rows, a.out / "scale.png") if rows else {}
    (a.out / "scale.json").write_text(
        json.dumps({"rows": rows, "scene": scene, "fits": fits}, indent=1, default=float)
    )
    cmd = f"python scripts/bench_scale.py --sizes {a.sizes} --scene {a.scene}"
    L = [
        "# `mvreg register` at scale (issue 14)",
        "",
        f"- Command: `{cmd}` ({datetime.date.today().isoformat()}); `OPENBLAS_NUM_THREADS=1`",
        f"- Machine: {machine()}",
        "- Data: `mvreg synth builtin --views V --points-per-scan "
        f"{a.points} --seed 1`; each row is one `mvreg register DIR --no-rrd` process",
        "- Load: the 1-minute load average when the run started (2 cores, shared with other",
        "  jobs: times are upper bounds)",
        "",
        "| set | scans | registered | total s | "
        + " | ".join(f"{s} s" for s in STAGES)
        + " | peak MiB | rot max deg | cand. pairs | refine pairs | load |",
        "| --- " * (9 + len(STAGES)) + "|",
    ]
    for r in [*rows, *([scene] if scene else [])]:
        L.append(_table_row(r))
    L += ["", "Fitted exponents (time ~ scans^k, builtin rows):", ""]
    L += [f"- {k}: {v:.2f}" for k, v in fits.items() if v is not None]
    L += ["", "![time against scans](scale.png)", "", NOTES]
    old = a.out / "scale.md"
    kept = old.read_text().split(NOTES, 1)[1] if old.exists() and NOTES in old.read_text() else ""
    (a.out / "scale.md").write_text("\n".join(L) + kept)
    print(f"wrote {a.out / 'scale.md'}", file=sys.stderr)


NOTES = "<!-- notes: the text below this line is kept when the tables are rewritten -->"


def _table_row(r: dict) -> str:
    if "timings" not in r:
        return f"| {r['set']} | {r['views']} | exit {r['exit']} |" + " |" * (8 + len(STAGES))
    t = r["timings"]
    stages = " | ".join(f"{t.get(s, float('nan')):.1f}" for s in STAGES)
    rot = "-" if r["rot_max"] is None else f"{r['rot_max']:.3f}"
    return (
        f"| {r['set']} | {r['scans']} | {r['registered']} | {t['total']:.1f} | {stages} | "
        f"{r['peak_rss_mib']:.0f} | {rot} | {r['candidate_pairs']} | "
        f"{'/'.join(map(str, r['refine_pairs']))} | {r['load_start']:.1f} |"
    )
