"""The registration pipeline: ``register(folder) -> Registration``.

Stages (one module each): load (:mod:`.load`), preprocess and pair graph (the mode,
:mod:`.stages`), the global stage (:mod:`mvreg.globalstage`), evaluation
(:mod:`.evaluate`); :mod:`.register` runs them in order. See docs/architecture.md.
"""

from mvreg.pipeline.load import load_source
from mvreg.pipeline.register import register, run_pipeline
from mvreg.pipeline.result import Registration, pair_table
from mvreg.pipeline.run import NoProgress, Run
from mvreg.pipeline.stages import Mode, PairGraph, UnorderedMode

__all__ = [
    "Mode",
    "NoProgress",
    "PairGraph",
    "Registration",
    "Run",
    "UnorderedMode",
    "load_source",
    "pair_table",
    "register",
    "run_pipeline",
]
