"""The result of a registration run (:class:`Registration`) and the pair table."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from mvreg.config import RegisterConfig
from mvreg.globalstage.verify import NOTE as VERIFICATION_NOTE
from mvreg.io.loaders import Scan
from mvreg.scales import Scales


@dataclass
class Registration:
    """The result of ``register``.

    T_world_scan: {scan name: (4, 4) world_from_scan} for every registered scan; the world
    frame is the first registered scan; every pose in it is verified
    (:mod:`mvreg.globalstage.verify`). ``unregistered`` lists the scans that could not be
    connected to the rest (never given a made-up pose); ``unverified`` and
    ``undetermined`` those left out because no independent evidence confirms their pose
    or a degree of freedom of it is not fixed by the data (``verification`` says why, per
    scan). ``solve`` is the last global solve: its certificate proves that solve optimal
    for the accepted pairs, not the pairs right. ``scales``: the lengths of the run.
    """

    scan_names: list[str]
    T_world_scan: dict[str, np.ndarray]
    unregistered: list[str]
    solve: object
    pairs: list[dict]
    config: RegisterConfig
    scales: Scales
    timings: dict
    robust_log: list[dict] = field(default_factory=list)
    refine_log: list[dict] = field(default_factory=list)
    joint_icp: dict | None = None  # the joint point-to-plane ICP after the rounds
    overlap: dict | None = None
    truth_errors: dict | None = None
    scans: list[Scan] = field(default_factory=list, repr=False)
    source: str | None = None
    skipped_files: list[dict] = field(default_factory=list)  # folder entries not read
    unverified: list[str] = field(default_factory=list)  # left out: pose not confirmed
    undetermined: list[str] = field(default_factory=list)  # left out: a free DOF
    verification: dict = field(default_factory=dict)  # {scan: status, reason, evidence}

    @property
    def voxel_size(self) -> float:
        return self.scales.voxel

    @property
    def all_registered(self) -> bool:
        """Every scan placed and its pose verified (what exit code 0 means)."""
        return not (self.unregistered or self.unverified or self.undetermined)

    def __repr__(self) -> str:
        c = self.solve.certificate if self.solve is not None else None
        return (
            f"{type(self).__name__}(scans={len(self.scan_names)}, "
            f"registered={len(self.T_world_scan)}, unregistered={self.unregistered}, "
            f"certified={c.certified if c else None}, "
            f"time={self.timings.get('total', float('nan')):.2f}s)"
        )

    def report(self) -> dict:
        """The content of report.json (the configuration with the resolved voxel size)."""
        s = self.solve
        config = self.config.model_dump(mode="json")
        config["preprocess"]["voxel_size"] = self.scales.voxel
        return {
            "format": "mvreg.report/1",
            "source": self.source,
            "config": config,
            "voxel_size": self.scales.voxel,
            "scales": self.scales.to_dict(),
            "scans": self.scan_names,
            "skipped_files": self.skipped_files,
            "registered": list(self.T_world_scan),
            "unregistered": self.unregistered,
            "unverified": self.unverified,
            "undetermined": self.undetermined,
            "verification": {"scans": self.verification, "note": VERIFICATION_NOTE},
            "timings_s": self.timings,
            "pairs": self.pairs,
            "bad_pairs": [p for p in self.pairs if p["accepted"] and p["final_weight"] == 0.0],
            "solver": None if s is None else s.to_dict(),
            "certificate": None if s is None or s.certificate is None else s.certificate.to_dict(),
            "robust_rounds": self.robust_log,
            "refine_rounds": self.refine_log,
            "joint_icp": self.joint_icp,
            "overlap_residual": self.overlap,
            "ground_truth_errors": self.truth_errors,
        }


def pair_table(
    results: Sequence, tracks, weights, extra: Callable[[object], dict] | None = None
) -> list[dict]:
    """One row per pair result: scores, accepted, final weight (0 when not accepted).

    ``extra(result)`` adds columns (the pair-graph stage's own, e.g. free-space scores
    or how a sequence pair was found)."""
    w_of = {(int(i), int(j)): float(w) for (i, j), w in zip(tracks.pairs, weights, strict=True)}
    rows = []
    for r in results:
        rows.append(
            {
                "scans": list(r.names),
                "accepted": bool(r.accepted),
                "reason": r.reason,
                "overlap_ratio": r.overlap_ratio,
                "inlier_rmse": r.inlier_rmse,
                "num_correspondences": int(r.num_correspondences),
                "fitness": r.fitness,
                "residual_ratio": r.residual_ratio,
                **(extra(r) if extra is not None else {}),
                "final_weight": w_of.get((r.i, r.j), 0.0) if r.accepted else 0.0,
                "seconds": r.seconds,
            }
        )
    return rows
