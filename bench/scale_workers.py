"""The pairwise stage on 1 and 2 local Dask worker processes (issue 14, item 4).

Synthesizes ``mvreg synth builtin --views 20 --points-per-scan 10000 --seed 1`` (data_synth),
preprocesses the scans once in-process, then times :func:`mvreg.pairwise.align_pairs` over
the run's candidate pairs (the pairwise stage of ``register``: the client-side preparation,
sending the scans to every worker once, and one task per pair) on a ``LocalCluster`` of
N worker processes (one thread each), ``--repeats`` times per N, each time with the scans
sent afresh (so every repetition pays the transfer and the workers' cache building), and
in-process on 1 and 2 threads for reference; the settings take turns, round by round. Every run must give the same pair poses bit
for bit. Records the machine, the load average before and after each measurement, the
pickled size of a pair task and of the shared scans, and each worker's resident memory.

Writes docs/benchmarks/workers.md (and workers.json).

    python scripts/bench_workers.py                       # 20 views, 10k points, 3 repeats
    python scripts/bench_workers.py --views 40 --repeats 5
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import ROOT, machine


def prepare(views: int, points: int, seed: int, tmp: Path):
    """(preprocessed scans, scales, candidate pairs, load config) of a synthetic set."""
    from data_synth import synthesize_scans
    from mvreg.config import load_config
    from mvreg.pairwise import candidate_pairs, derive_scales, preprocess_all, with_noise
    from mvreg.pipeline.load import load_source
    from mvreg.pipeline.run import NoProgress

    synthesize_scans("builtin", tmp, views=views, points_per_scan=points, seed=seed)
    cfg = load_config(seed=seed)
    scans = load_source(tmp, None, cfg.min_points, None, None, NoProgress()).scans
    scales = derive_scales(scans, cfg.preprocess, 2)
    pre = preprocess_all(scans, scales.voxel, cfg.preprocess, 2)
    return pre, with_noise(scales, pre), candidate_pairs(pre, cfg.pairs), cfg


def run_once(pre, scales, pairs, cfg, executor, row: dict) -> None:
    """One timed pairwise stage on ``executor``, appended to ``row``."""
    from mvreg.pairwise import align_pairs

    if hasattr(executor, "forget"):
        executor.forget()  # the scans are sent again: every repetition pays for it
    load0, cpu0 = os.getloadavg()[0], worker_cpu(executor)
    t0 = time.perf_counter()
    res = align_pairs(pre, pairs, cfg.align, cfg.seed, executor=executor, scales=scales)
    row["walls"].append(time.perf_counter() - t0)
    row["loads"].append((load0, os.getloadavg()[0]))
    row["worker_cpu_s"].append([b - a for a, b in zip(cpu0, worker_cpu(executor), strict=True)])
    row["poses"] = np.stack([r.T_i_j for r in res])
    if hasattr(executor, "task_bytes"):
        row |= {"task_bytes": executor.task_bytes, "shared_bytes": executor.shared_bytes}


def worker_cpu(executor) -> list[float]:
    """CPU seconds (user + system) used so far by each worker process (in-process: this
    process), in the order of the workers' addresses."""

    def cpu() -> float:
        t = os.times()
        return t.user + t.system

    if not hasattr(executor, "client"):
        return [cpu()]
    return [v for _, v in sorted(executor.client.run(cpu).items())]


def worker_memory(executor) -> list[float]:
    """Resident memory (MiB) of each worker process."""

    def rss() -> float:
        import psutil

        return psutil.Process().memory_info().rss / 2**20

    return sorted(executor.client.run(rss).values())


def warm(executor) -> None:
    """Import the pairwise modules (Open3D, SciPy) on every worker before timing."""

    def imports() -> None:
        import mvreg.pairwise.aligners  # noqa: F401

    executor.client.run(imports)


def measure(a, pre, scales, pairs, cfg) -> dict:
    """Every setting once per round, ``a.repeats`` rounds: the settings see the same load
    (other jobs on the machine come and go) and each round gives a paired ratio."""
    from mvreg.distributed import DaskExecutor
    from mvreg.executor import ThreadExecutor

    settings = [(f"threads {n}", ThreadExecutor(n)) for n in a.threads]
    rows = {}
    with contextlib.ExitStack() as stack:
        for n in a.workers:
            t0 = time.perf_counter()
            ex = stack.enter_context(DaskExecutor.local(n))
            warm(ex)
            settings.append((f"workers {n}", ex))
            rows[f"workers {n}"] = {
                "start_cluster": time.perf_counter() - t0,
                "worker_rss_idle_mib": worker_memory(ex),
            }
        for name, _ in settings:
            rows.setdefault(name, {}).update(walls=[], loads=[], worker_cpu_s=[])
        for k in range(a.repeats):
            for name, ex in settings:
                print(f"round {k + 1}: {name} ...", file=sys.stderr)
                run_once(pre, scales, pairs, cfg, ex, rows[name])
        for name, ex in settings:
            rows[name]["median"] = float(np.median(rows[name]["walls"]))
            if hasattr(ex, "client"):
                rows[name]["worker_rss_mib"] = worker_memory(ex)
    return {name: rows[name] for name, _ in settings}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--views", type=int, default=20)
    ap.add_argument("--points-per-scan", type=int, default=10000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=3, help="timed runs per setting (median)")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks")
    a = ap.parse_args(argv)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    load_start = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmp:
        pre, scales, pairs, cfg = prepare(a.views, a.points_per_scan, a.seed, Path(tmp) / "s")
    rows = measure(a, pre, scales, pairs, cfg)
    first = next(iter(rows.values()))["poses"]
    identical = all(np.array_equal(r["poses"], first) for r in rows.values())
    scan_bytes = [len(__import__("pickle").dumps(p)) for p in pre]
    write_report(a, rows, identical, len(pairs), scan_bytes, load_start)


def _loads(r: dict) -> str:
    return "; ".join(f"{x:.1f} -> {y:.1f}" for x, y in r["loads"])


def write_report(a, rows, identical, n_pairs, scan_bytes, load_start) -> None:
    a.out.mkdir(parents=True, exist_ok=True)
    cmd = "python scripts/bench_workers.py" + "".join(
        f" --{k} {v}"
        for k, v in (("views", a.views), ("points-per-scan", a.points_per_scan))
        if v != {"views": 20, "points-per-scan": 10000}[k]
    )
    w1, w2 = rows.get("workers 1"), rows.get("workers 2")
    speedup = w1["median"] / w2["median"] if w1 and w2 else float("nan")
    paired = np.divide(w1["walls"], w2["walls"]) if w1 and w2 else np.array([np.nan])
    mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    L = [
        "# The pairwise stage on 1 and 2 local Dask worker processes",
        "",
        f"- Command: `OPENBLAS_NUM_THREADS=1 {cmd}` ({datetime.date.today().isoformat()})",
        f"- Machine: {machine()}; `nproc` {os.cpu_count()}, RAM {mem:.1f} GiB",
        f"- Load average (1, 5, 15 min) at the start: {', '.join(f'{x:.2f}' for x in load_start)}",
        f"- Data: `mvreg synth builtin --views {a.views} --points-per-scan {a.points_per_scan} "
        f"--seed {a.seed}` (data_synth), {n_pairs} candidate pairs, preprocessed once in-process",
        "- Timed: `align_pairs` over the candidate pairs (the pairwise stage of `register`: "
        "the client-side preparation, the scans sent to every worker once by content key, "
        f"one task per pair), {a.repeats} rounds of every setting in turn (so that the settings "
        "share the load of the moment), the scans sent afresh each run; the clusters are "
        "started and their workers have imported Open3D before timing.",
        f"- Pair poses identical bit for bit in every setting: **{identical}**",
        "",
        "| setting | median s | runs (s) | CPU s per worker process, each run | "
        "1-min load before -> after each run |",
        "|---|---|---|---|---|",
    ]
    for name, r in rows.items():
        walls = ", ".join(f"{w:.2f}" for w in r["walls"])
        cpu = "; ".join(" + ".join(f"{c:.1f}" for c in run) for run in r["worker_cpu_s"])
        cpu = cpu if name.startswith("workers") else f"({cpu}: the whole process)"
        L.append(f"| {name} | {r['median']:.2f} | {walls} | {cpu} | {_loads(r)} |")
    L += [
        "",
        f"**Speedup of 2 worker processes over 1: {speedup:.2f}x** (ratio of the medians; "
        f"per round: {', '.join(f'{x:.2f}' for x in paired)}; target >= 1.6x: "
        f"{'met' if speedup >= 1.6 else 'not met'}).",
        "",
    ]
    busiest = max(max(x, y) for r in rows.values() for x, y in r["loads"])
    if busiest > os.cpu_count():
        L += [
            f"Measured under load: the 1-minute load average reached {busiest:.1f} on "
            f"{os.cpu_count()} cores during the runs (other engineers' jobs), so the worker "
            "processes shared the cores with other work; these times are upper bounds and "
            "the speedup is not what idle cores give. The CPU seconds per worker show how "
            "the work was split.",
            "",
        ]
    if w2:
        grown = np.subtract(w2["worker_rss_mib"], w2["worker_rss_idle_mib"])
        per_scan = float(np.mean(grown)) / len(scan_bytes)
        L += [
            f"- Pickled size of a pair task: {w2['task_bytes']} bytes; of one preprocessed scan: "
            f"{min(scan_bytes) / 2**20:.2f}-{max(scan_bytes) / 2**20:.2f} MiB; of all "
            f"{len(scan_bytes)} scans sent to each worker once: {w2['shared_bytes'] / 2**20:.1f} "
            "MiB.",
            f"- Local cluster start: {w2['start_cluster']:.1f} s (2 workers); resident memory "
            "per worker after the runs: "
            + ", ".join(f"{m:.0f} MiB" for m in w2["worker_rss_mib"])
            + f" (1 worker: {', '.join(f'{m:.0f} MiB' for m in w1['worker_rss_mib'])}); "
            "before any scan, with Open3D imported: "
            + ", ".join(f"{m:.0f} MiB" for m in w2["worker_rss_idle_mib"])
            + f"; so about {per_scan:.1f} MiB per scan on each worker (the preprocessed "
            "scan and its caches).",
        ]
    (a.out / "workers.md").write_text("\n".join(L) + "\n")
    js = {k: {x: y for x, y in r.items() if x != "poses"} for k, r in rows.items()}
    js |= {"speedup_2_over_1": speedup, "identical": identical, "load_start": load_start}
    (a.out / "workers.json").write_text(json.dumps(js, indent=1) + "\n")
    print("\n".join(L))
