"""The result of a registration run (:class:`Registration`) and the pair table."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from mvreg.config import RegisterConfig
from mvreg.globalstage.verify import NOTE as VERIFICATION_NOTE
from mvreg.globalstage.verify import ScanVerification
from mvreg.io.loaders import Scan
from mvreg.io.poses import pose_with_offset
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

    Scans the load stage left out (fewer than ``min_points`` points) are in
    ``rejected_scans`` (``{"scan", "file", "reason"}``) and in ``unregistered``, with
    the reason in ``verification``; ``scan_names`` and ``scans`` are the scans that were
    registered, in order.

    Local frame: when the scans were far from their origin (georeferenced), the load
    stage subtracted ``local_frame_offset`` from every one of them; ``scans``,
    ``T_world_scan`` and the evaluation are then in that local frame, and
    :meth:`T_world_scan_in_file_frame` gives the poses in the files' own coordinates
    (what the output files hold). Without an offset the two are the same.
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
    stored_pose_differences: dict | None = None  # against the files' own poses (E57)
    scans: list[Scan] = field(default_factory=list, repr=False)
    source: str | None = None
    skipped_files: list[dict] = field(default_factory=list)  # folder entries not read
    unverified: list[str] = field(default_factory=list)  # left out: pose not confirmed
    undetermined: list[str] = field(default_factory=list)  # left out: a free DOF
    verification: dict = field(default_factory=dict)  # {scan: status, reason, evidence}
    rejected_scans: list[dict] = field(default_factory=list)  # left out: too few points
    truth_without_scan: list[str] = field(default_factory=list)  # truth names no scan has

    def __post_init__(self) -> None:
        # The load stage hands the scans it left out (too few points) over with the
        # skipped files (entries with a "scan" key): they are scans of the input, so
        # they are reported as unregistered, with the reason.
        left_out = [s for s in self.skipped_files if "scan" in s]
        if not left_out:
            return
        self.skipped_files = [s for s in self.skipped_files if "scan" not in s]
        self.rejected_scans = [*self.rejected_scans, *left_out]
        self.unregistered = [*self.unregistered, *(s["scan"] for s in left_out)]
        self.verification = {
            **self.verification,
            **{
                s["scan"]: ScanVerification("unregistered", s["reason"]).to_dict() for s in left_out
            },
        }

    @property
    def local_frame_offset(self) -> np.ndarray | None:
        """(3,) float64 the load stage subtracted from every scan (None: no shift)."""
        return next(
            (s.local_frame_offset for s in self.scans if s.local_frame_offset is not None), None
        )

    def T_world_scan_in_file_frame(self) -> dict[str, np.ndarray]:
        """{scan name: (4, 4)} ``T_world_scan`` mapping the files' own coordinates to the
        world frame (the first registered scan's file frame); ``T_world_scan`` itself when
        there is no local frame offset."""
        offset = self.local_frame_offset
        if offset is None:
            return dict(self.T_world_scan)
        return {n: pose_with_offset(T, offset) for n, T in self.T_world_scan.items()}

    @property
    def all_scan_names(self) -> list[str]:
        """Every scan of the input: the registered run's, then those left out at loading."""
        return [*self.scan_names, *(s["scan"] for s in self.rejected_scans)]

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
        offset = self.local_frame_offset
        config = self.config.model_dump(mode="json")
        config["preprocess"]["voxel_size"] = self.scales.voxel
        return {
            "format": "mvreg.report/1",
            "source": self.source,
            "config": config,
            "voxel_size": self.scales.voxel,
            "scales": self.scales.to_dict(),
            "scans": self.all_scan_names,
            # Poses and merged cloud are in the files' frame; the solver, pairs and
            # evaluation in the local frame (file coordinates minus this offset).
            "local_frame_offset": None if offset is None else offset.tolist(),
            "skipped_files": self.skipped_files,
            "rejected_scans": self.rejected_scans,
            "ground_truth_without_scan": self.truth_without_scan,
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
            # Against the poses the files store (E57 scan headers), when 2+ have one.
            "stored_pose_differences": self.stored_pose_differences,
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
