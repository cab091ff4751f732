"""The pairwise aligner interface and the registry of named aligners.

An aligner proposes and verifies the relative pose of two preprocessed scans::

    aligner = make_aligner("feature-ransac", cfg.align, cfg.search, scales=scales)
    aligner.prepare(pre)        # once per run, with all scans, before any pair
    res = aligner.align(pre[i], pre[j], guess=None, seed=pair_seed(seed, i, j), i=i, j=j)

Contract of :meth:`PairwiseAligner.align`: ``guess`` is a (4, 4) initial ``T_i_j`` (scan
j into scan i's frame) or None; an aligner that searches ignores it, ``icp-guess``
starts from it (identity when None). It returns a
:class:`~mvreg.pairwise.result.PairResult` decided by the acceptance rule every aligner
shares (:func:`mvreg.pairwise.decision.decide`), deterministic for a given ``seed``;
``i`` and ``j`` only label the result. ``prepare(pre)`` gets every scan of the run once
before pairs are aligned, possibly on several threads afterwards: run-wide state and the
scans' shared caches are built there, never lazily from two threads.

A factory (:data:`ALIGNERS`, :func:`make_aligner`) takes the ``align`` and ``search``
sections of the configuration and plain values: ``scales`` (the run's
:class:`~mvreg.scales.Scales`; None: those each scan was preprocessed at) and
``executor`` (for work inside one pair; pairs themselves are spread by
:func:`~mvreg.pairwise.align.align_pairs`).

Registered: ``feature-ransac`` (FPFH matches, RANSAC, ICP from several hypotheses; the
default of :func:`~mvreg.pairwise.align.align_pairs`), ``icp-guess`` (ICP from a given
pose: sequences), ``rotation-search`` (ICP from 240 start rotations: scans feature
matching leaves unconnected, :func:`~mvreg.pairwise.search.connect_unconnected`).

A new method is one new file plus one registry line. For example ICP from the scans'
own frames, for scans that come roughly aligned::

    # mvreg/pairwise/aligners/identity_icp.py
    import time

    import numpy as np

    from mvreg.pairwise.aligners.base import BaseAligner, register_aligner
    from mvreg.pairwise.decision import verify
    from mvreg.pairwise.result import pair_result


    @register_aligner("identity-icp")
    class IdentityIcpAligner(BaseAligner):
        def align(self, pre_i, pre_j, guess=None, seed=0, *, i=0, j=1):
            start, scales = time.perf_counter(), self.scales_for(pre_i)
            T0 = np.eye(4) if guess is None else guess
            T, reason, scores, _ = verify(pre_i, pre_j, T0, self.cfg, scales)
            return pair_result(pre_i, pre_j, i, j, T, reason, scores, {}, start,
                               fine_voxel=scales.fine_voxel)

    # mvreg/pairwise/aligners/__init__.py, the registry line:
    from mvreg.pairwise.aligners import identity_icp  # noqa: F401

after which ``align_pairs(pre, pairs, cfg.align, method="identity-icp")`` runs it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from mvreg.config.align import AlignConfig, SearchConfig
from mvreg.errors import ConfigError
from mvreg.executor import Executor, make_executor
from mvreg.pairwise.preprocess import PreprocessedScan, scan_scales
from mvreg.pairwise.result import PairResult
from mvreg.pairwise.scoring import prepare_scans
from mvreg.scales import Scales


@runtime_checkable
class PairwiseAligner(Protocol):
    """Aligns scan j to scan i; see the module docstring for the contract."""

    def prepare(self, pre: Sequence[PreprocessedScan]) -> None:
        """Run-wide state and shared caches, from all scans of the run (called once)."""

    def align(
        self,
        pre_i: PreprocessedScan,
        pre_j: PreprocessedScan,
        guess: np.ndarray | None = None,
        seed: int = 0,
        *,
        i: int,
        j: int,
    ) -> PairResult:
        """The decided PairResult of scan j onto scan i (``T_i_j``)."""


class BaseAligner:
    """What most aligners share (a convenience, not part of the contract): the sections
    and plain values of the factory, :meth:`prepare` building the scans' shared caches,
    and :meth:`scales_for` (the run's scales, else those of the scan)."""

    def __init__(
        self,
        align: AlignConfig | None = None,
        search: SearchConfig | None = None,
        *,
        scales: Scales | None = None,
        executor: Executor | int = 1,
    ):
        self.cfg = align or AlignConfig()
        self.search = search or SearchConfig()
        self.scales = scales
        self.executor = make_executor(executor)

    def prepare(self, pre: Sequence[PreprocessedScan]) -> None:
        """Build the scans' shared caches (KD-trees, depth grids) before threads share them."""
        prepare_scans(pre, self.scales)

    def scales_for(self, pre_i: PreprocessedScan) -> Scales:
        """The run's scales, else those ``pre_i`` was preprocessed at."""
        return scan_scales(pre_i) if self.scales is None else self.scales


AlignerFactory = Callable[..., PairwiseAligner]
"""``factory(align: AlignConfig, search: SearchConfig, *, scales: Scales | None,
executor: Executor | int) -> PairwiseAligner``."""

ALIGNERS: dict[str, AlignerFactory] = {}
"""Registered aligners by name (filled by :func:`register_aligner`)."""


def register_aligner(name: str) -> Callable[[AlignerFactory], AlignerFactory]:
    """Class (or factory) decorator: make it available as ``name`` in :data:`ALIGNERS`."""

    def add(factory: AlignerFactory) -> AlignerFactory:
        if name in ALIGNERS and ALIGNERS[name] is not factory:
            raise ValueError(f"an aligner named {name!r} is already registered")
        ALIGNERS[name] = factory
        return factory

    return add


def make_aligner(
    name: str,
    align: AlignConfig | None = None,
    search: SearchConfig | None = None,
    *,
    scales: Scales | None = None,
    executor: Executor | int = 1,
) -> PairwiseAligner:
    """The registered aligner ``name`` for these settings (ConfigError when unknown)."""
    if name not in ALIGNERS:
        raise ConfigError(f"unknown pairwise aligner {name!r}; known: {', '.join(ALIGNERS)}")
    return ALIGNERS[name](
        align or AlignConfig(), search or SearchConfig(), scales=scales, executor=executor
    )
