"""Pairs from the poses stored in the files: a second chance for pairs features missed.

Takes the preprocessed scans, the loaded scans (their ``T_world_scan_hint``: the scanner
pose an E57 file stores), the pair results of the feature aligner and the ``align``
section. Returns the results with every pair that was rejected, and whose two scans both
carry a stored pose, tried again by point-to-plane ICP from the relative pose the stored
poses give (``icp-guess``), kept when that passes the same acceptance rule
(``stats["init"] == "stored poses"``). A stored pose is a hint, never trusted: a pair the
features accepted keeps its own pose (``report.json`` compares the result with the
stored poses: ``stored_pose_differences``), and a pair the hint places wrongly fails the
rule like any other. Without stored poses nothing runs. Deterministic (ICP only).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mvreg.config.align import AlignConfig
from mvreg.geometry import invert_transform
from mvreg.pairwise.aligners import make_aligner
from mvreg.pairwise.result import PairResult
from mvreg.scales import Scales


def retry_from_stored_poses(
    pre: Sequence,
    scans: Sequence,
    results: Sequence[PairResult],
    cfg: AlignConfig,
    scales: Scales | None = None,
) -> list[PairResult]:
    """``results`` with rejected pairs retried from the stored poses (module docstring)."""
    hints = [getattr(s, "T_world_scan_hint", None) for s in scans]
    if sum(h is not None for h in hints) < 2:
        return list(results)
    icp = make_aligner("icp-guess", cfg, None, scales=scales)
    out = []
    for r in results:
        Hi, Hj = hints[r.i], hints[r.j]
        if r.accepted or Hi is None or Hj is None:
            out.append(r)
            continue
        guess = invert_transform(np.asarray(Hi)) @ np.asarray(Hj)
        retried = icp.align(pre[r.i], pre[r.j], guess, i=r.i, j=r.j)
        retried.stats["init"] = "stored poses"
        retried.stats["features"] = r.reason
        out.append(retried if retried.accepted else r)
    return out
