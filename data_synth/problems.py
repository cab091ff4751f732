"""Synthetic patch problems with known ground truth (for tests and benchmarks).

Patches are placed in space (centres ~1 apart); each edge (i, j) of a sparse overlap
graph gets ``nodes_per_pair`` nodes scattered in a ball of radius 0.5 around the midpoint
of the two centres, seen by both patches. Every patch has its own random rotation and a
translation of the order of the scene size. Noise is Gaussian with standard deviation
``noise`` times the patch size (patches are ~1 across), added to the local coordinates.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from mvreg.errors import InputError
from mvreg.geometry import random_rotations
from mvreg.solver.problem import PatchProblem


@dataclass
class SyntheticTruth:
    """Ground truth: R_world_patch (M, d, d), t_world_patch (M, d), nodes (N, d),
    edges (E, 2) of the overlap graph, outlier mask (K,) of the observations."""

    rotations: np.ndarray
    translations: np.ndarray
    nodes: np.ndarray
    edges: np.ndarray
    outliers: np.ndarray


def overlap_graph(
    rng: np.random.Generator, m: int, d: int, degree: int, graph: str = "geometric"
) -> tuple[np.ndarray, np.ndarray]:
    """Patch centres (M, d) and undirected edges (E, 2) with mean degree ~``degree``.

    ``geometric``: centres uniform in a box of ~unit density, each joined to its
    nearest neighbours (a spatial layout like scans of a scene). ``random``: each patch
    joined to random others (an expander-like graph). ``complete``: all pairs.
    """
    side = m ** (1.0 / d)
    centres = rng.uniform(0, side, size=(m, d))
    if m == 1:
        return centres, np.zeros((0, 2), dtype=np.int64)
    if graph == "complete" or m <= degree + 1:
        i, j = np.triu_indices(m, 1)
        return centres, np.stack([i, j], 1)
    if graph == "geometric":
        # k nearest neighbours, symmetrized; the smallest k whose mean degree >= degree.
        kmax = min(m - 1, 2 * degree + 2)
        _, nn = cKDTree(centres).query(centres, k=kmax + 1)
        for k in range(1, kmax + 1):
            i = np.repeat(np.arange(m), k)
            j = nn[:, 1 : k + 1].ravel()
            e = np.unique(np.sort(np.stack([i, j], 1), axis=1), axis=0)
            if 2 * len(e) / m >= degree:
                break
    elif graph == "random":
        k = max(1, int(round(degree / 2)))
        i = np.repeat(np.arange(m), k)
        j = (i + rng.integers(1, m, size=i.shape[0])) % m
    else:
        raise ValueError(f"unknown graph {graph!r}")
    e = np.unique(np.sort(np.stack([i, j], 1), axis=1), axis=0)
    e = e[e[:, 0] != e[:, 1]]
    # Join components (rare for k-NN graphs) by their closest centres.
    while True:
        adj = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(m, m))
        nc, lab = connected_components(adj, directed=False)
        if nc == 1:
            break
        a = np.flatnonzero(lab == 0)
        b = np.flatnonzero(lab != 0)
        dist, idx = cKDTree(centres[b]).query(centres[a])
        s = int(np.argmin(dist))
        e = np.vstack([e, np.sort([a[s], b[idx[s]]])])
    return centres, e


def problem_bytes(num_patches: int, d: int, degree: int, nodes_per_pair: int) -> float:
    """Peak memory of :func:`make_problem` (bytes, an estimate from above): per
    observation its coordinates, indices and the gathered rotation of its patch."""
    observations = float(num_patches) * degree * nodes_per_pair  # 2 per shared node
    return observations * (8 * d * d + 32 * d + 96) + float(num_patches) * 64 * d


def check_problem_size(num_patches: int, d: int, degree: int, nodes_per_pair: int) -> None:
    """InputError naming the sizes when :func:`make_problem` would need more than half of
    this machine's memory (checked before anything is allocated; a degree of M - 1 or more
    is a complete overlap graph)."""
    need = problem_bytes(num_patches, d, min(degree, num_patches - 1), nodes_per_pair)
    have = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    if need > have / 2:
        raise InputError(
            f"--patches {num_patches} with --degree {degree} and --nodes-per-pair "
            f"{nodes_per_pair}: needs about {need / 2**30:.3g} GiB, more than half of this "
            f"machine's {have / 2**30:.3g} GiB"
        )


def make_problem(
    num_patches: int,
    d: int = 3,
    degree: int = 6,
    nodes_per_pair: int = 20,
    noise: float = 0.0,
    outlier_fraction: float = 0.0,
    graph: str = "geometric",
    seed: int = 0,
) -> tuple[PatchProblem, SyntheticTruth]:
    """A random REG instance and its ground truth (see module docstring)."""
    check_problem_size(num_patches, d, degree, nodes_per_pair)
    rng = np.random.default_rng(seed)
    m = int(num_patches)
    centres, edges = overlap_graph(rng, m, d, degree, graph)
    ne = edges.shape[0]
    npp = int(nodes_per_pair)
    # Nodes: npp per edge, in a ball of radius 0.5 around the edge midpoint.
    mid = 0.5 * (centres[edges[:, 0]] + centres[edges[:, 1]])
    u = rng.standard_normal((ne, npp, d))
    u /= np.linalg.norm(u, axis=2, keepdims=True)
    rad = 0.5 * rng.uniform(0, 1, size=(ne, npp, 1)) ** (1.0 / d)
    z = (mid[:, None, :] + u * rad).reshape(-1, d)
    node = np.arange(ne * npp)
    obs_patch = np.concatenate([np.repeat(edges[:, 0], npp), np.repeat(edges[:, 1], npp)])
    obs_node = np.concatenate([node, node])
    rot = random_rotations(rng, m, d)
    trans = rng.uniform(-1, 1, size=(m, d)) * (m ** (1.0 / d) + 1.0)
    # x = R^T (z - t) + noise
    x = np.einsum("kji,kj->ki", rot[obs_patch], z[obs_node] - trans[obs_patch])
    if noise > 0:
        x += noise * rng.standard_normal(x.shape)
    outl = np.zeros(x.shape[0], dtype=bool)
    if outlier_fraction > 0:
        outl = rng.uniform(size=x.shape[0]) < outlier_fraction
        # An outlier sees a random point of its patch's neighbourhood.
        x[outl] = rng.uniform(-1.0, 1.0, size=(int(outl.sum()), d)) + np.einsum(
            "kji,kj->ki", rot[obs_patch[outl]], centres[obs_patch[outl]] - trans[obs_patch[outl]]
        )
    problem = PatchProblem(coords=x, patch=obs_patch, node=obs_node, num_patches=m)
    truth = SyntheticTruth(rot, trans, z, edges, outl)
    return problem, truth
