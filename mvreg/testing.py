"""Helpers for robustness tests and benchmarks (not used by the pipeline itself)."""

from __future__ import annotations

import dataclasses

import numpy as np

from mvreg.geometry import invert_transform, transform_points


def wrong_pair_injector(
    truth: dict[str, np.ndarray],
    count: int = 2,
    seed: int = 0,
    angle_deg: float = 12.0,
    shift_voxels: float = 1.5,
):
    """A ``pair_hook`` that replaces ``count`` pairs by plausible but wrong alignments.

    The chosen pairs (those with the largest true overlap that are not already wrong,
    picked at random among the top half) get the true relative pose perturbed by a
    rotation of ``angle_deg`` about the overlap centroid and a shift of ``shift_voxels``
    feature voxels, and are marked accepted: like a slide along a near-symmetric surface.
    The hook records the injected pairs in its ``injected`` attribute (scan-name pairs).
    """

    def hook(pre, results):
        from scipy.spatial.transform import Rotation

        rng = np.random.default_rng(seed)
        names = [p.name for p in pre]
        ranked = sorted(
            (r for r in results if names[r.i] in truth and names[r.j] in truth),
            key=lambda r: -r.overlap_ratio,
        )
        pool = ranked[: max(count, len(ranked) // 2)]
        chosen = rng.choice(len(pool), size=min(count, len(pool)), replace=False)
        out = list(results)
        hook.injected = []
        for c in chosen:
            r = pool[c]
            T_true = invert_transform(truth[names[r.i]]) @ truth[names[r.j]]
            centre = transform_points(T_true, pre[r.j].points).mean(axis=0)
            axis = rng.normal(size=3)
            R = Rotation.from_rotvec(
                np.radians(angle_deg) * axis / np.linalg.norm(axis)
            ).as_matrix()
            shift = rng.normal(size=3)
            shift *= shift_voxels * pre[r.i].voxel_size / np.linalg.norm(shift)
            P = np.eye(4)
            P[:3, :3] = R
            P[:3, 3] = centre - R @ centre + shift
            wrong = dataclasses.replace(r, T_i_j=P @ T_true, accepted=True, reason="")
            out[out.index(r)] = wrong
            hook.injected.append((names[r.i], names[r.j]))
        return out

    hook.injected = []
    return hook
