"""mvreg in the peer benchmark: the default run, and its variants on the same pair graph.

:func:`run_default` runs ``mvreg.pipeline.register`` and keeps what the global stage got
(scales, preprocessed scans, pair results after the rotation search). :func:`rerun_global`
runs the pipeline again with other settings (another ``solve.solver``, no refinement) on
those cached stages, through the public staged API: ``run_pipeline`` with
:class:`CachedMode`, a mode whose preprocessing and pair graph return the cached results.
So only the global stage differs between the variants.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

from mvreg.config import load_config
from mvreg.globalstage.stage import MultiviewPlan
from mvreg.pipeline import PairGraph, Registration, Run, register, run_pipeline
from mvreg.pipeline.stages import free_space_columns


@dataclass
class Cached:
    """What the global stage of the default run received."""

    scales: object
    pre: list
    results: list


class CachedMode:
    """A mode (:class:`mvreg.pipeline.Mode`) replaying cached preprocessing and pairs.

    The evaluation is left out: the benchmark evaluates every method itself.
    """

    what = "registration"

    def __init__(self, cached: Cached):
        self.cached = cached

    def preprocess(self, run: Run, scans):
        by_name = {p.name: p for p in self.cached.pre}
        return self.cached.scales, [by_name[s.name] for s in scans]

    def pair_graph(self, run: Run, scans, pre, scales) -> PairGraph:
        results = copy.deepcopy(self.cached.results)
        run.timed("pairwise")
        return PairGraph(results, MultiviewPlan(), columns=free_space_columns)

    def evaluate(self, run: Run, reg, pre, results, truth) -> None:
        return None


def run_default(folder, truth, seed: int) -> tuple[Registration, Cached]:
    """``register(folder)`` with default settings and the stages its global stage saw."""
    cap = {}

    def hook(pre, results):
        cap["pre"], cap["results"] = pre, copy.deepcopy(results)
        return results

    reg = register(folder, truth=truth, pair_hook=hook, seed=seed)
    return reg, Cached(reg.scales, cap["pre"], cap["results"])


def rerun_global(source, cached: Cached, truth=None, **overrides) -> Registration:
    """The pipeline on ``source`` (the folder of the default run, loaded again: the global
    stage resamples the raw scans) with ``overrides`` (dotted keys, e.g.
    ``**{"solve.solver": "gpm"}``), reusing ``cached`` preprocessing and pairs."""
    cfg = load_config(**overrides)
    return run_pipeline(Run(cfg), CachedMode(cached), source, truth=truth)


def global_seconds(timings: dict) -> float:
    """Seconds of the global stage (tracks and solve, robust rounds, refinement)."""
    t = timings
    return t.get("tracks_and_solve", 0) + t.get("robust", 0) + t.get("refine", 0)
