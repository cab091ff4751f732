"""Chaining: pairwise registrations composed in scan order (scan k+1 into scan k).

What a user does by hand. ``chain/mvreg-pairs`` composes mvreg's pairwise transforms
(:func:`chain_mvreg_pairs`); ``chain/open3d-pairs`` is the odometry start of Open3D's pose
graph (computed in :func:`bench.peers.open3d.run_open3d_own`).
"""

from __future__ import annotations

import numpy as np

from mvreg.pairwise import align_pair


def chain_mvreg_pairs(pre, results, align_cfg, seed: int, scales=None):
    """``({k: T_world_k}, pairwise seconds)`` from ``results`` of pairs (k, k+1); a pair
    that was not a candidate (more scans than ``all_pairs_max_scans``) is aligned here."""
    by_pair = {(r.i, r.j): r for r in results}
    chain = {0: np.eye(4)}
    secs = 0.0
    for k in range(len(pre) - 1):
        r = by_pair.get((k, k + 1))
        if r is None:
            r = align_pair(pre[k], pre[k + 1], align_cfg, seed, i=k, j=k + 1, scales=scales)
        chain[k + 1] = chain[k] @ np.asarray(r.T_i_j)
        secs += r.seconds
    return chain, secs
