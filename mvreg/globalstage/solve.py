"""The global solve over tracks: a patch problem in, the poses of its scans out.

Takes a :class:`~mvreg.pairwise.tracks.Tracks` (its ``problem`` a PatchProblem over the
scans it links) and the ``solve`` section; returns a :class:`GlobalSolution` holding one
``T_world_scan`` per scan of the problem (the first scan of the problem is the world
frame) and the solver's result with its certificate. Scans no track reaches get no pose.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mvreg.config.solve import SolveConfig
from mvreg.pairwise import Tracks
from mvreg.solver import IterationRecord, SolveResult, solve


@dataclass
class GlobalSolution:
    """Poses of the registered scans and the solve that produced them.

    T_world_scan: {scan index: (4, 4)}; the world frame is the first registered scan.
    """

    T_world_scan: dict[int, np.ndarray]
    result: SolveResult
    tracks: Tracks


class TrackSolver:
    """Solves the patch problem of tracks with one solve section, seed and callback.

    ``solver(tracks, init=None)``: ``init`` is {scan: (4, 4)} poses to warm-start from
    (used when it covers every scan of the problem; else the spectral start).
    ``callback`` receives each solver IterationRecord, then one record per solve.
    """

    def __init__(self, cfg: SolveConfig, seed: int = 0, callback: Callable | None = None):
        self.cfg = cfg
        self.seed = seed
        self.callback = callback

    def __call__(self, tracks: Tracks, init: dict[int, np.ndarray] | None = None) -> GlobalSolution:
        problem = tracks.problem
        scans = [int(s) for s in tracks.patch_scans]
        R0 = "spectral"
        if init is not None and all(s in init for s in scans):
            R0 = np.stack([init[s][:3, :3] for s in scans])
        res = solve(problem, self.cfg, init=R0, seed=self.seed, callback=self.callback)
        if self.callback is not None:  # one point per global solve, after its iterations
            c = res.certificate
            self.callback(
                IterationRecord(
                    res.iterations,
                    res.objective,
                    c.kkt_residual if c is not None else float("nan"),
                    0.0,
                    res.rho_final if res.rho_final is not None else float("nan"),
                )
            )
        poses = {scan: T for scan, T in zip(scans, res.T_world_patch, strict=True)}
        return GlobalSolution(poses, res, tracks)


def max_translation_change(new: GlobalSolution, old: GlobalSolution) -> float:
    """Largest change of a scan's translation between two solutions (data units)."""
    return max(
        float(np.linalg.norm(new.T_world_scan[s][:3, 3] - old.T_world_scan[s][:3, 3]))
        for s in new.T_world_scan
        if s in old.T_world_scan
    )
