"""Spanning trees over pair edges: the largest connected set, poses composed along a BFS tree.

Edges are ``(i, j)`` scan indices; relative poses ``rel[(i, j)] = T_i_j`` map scan j into
scan i. Used to start Open3D's pose graph and to pick GTSAM's component.
"""

from __future__ import annotations

from collections import deque

import numpy as np


def main_root(n: int, edges: list[tuple[int, int]]) -> int:
    """Smallest scan index of the largest connected set (what register keeps)."""
    best, seen = (0, 0), set()
    for k in range(n):
        if k not in seen:
            comp, _ = largest_component(n, edges, k)
            seen |= comp
            best = max(best, (len(comp), -k))
    return -best[1]


def largest_component(n: int, edges: list[tuple[int, int]], root: int = 0):
    """BFS from ``root``: (reachable set, parent dict) over undirected edges."""
    adj: dict[int, list[int]] = {k: [] for k in range(n)}
    for i, j in edges:
        adj[i].append(j)
        adj[j].append(i)
    parent = {root: None}
    q = deque([root])
    while q:
        u = q.popleft()
        for w in adj[u]:
            if w not in parent:
                parent[w] = u
                q.append(w)
    return set(parent), parent


def poses_from_tree(n, rel: dict[tuple[int, int], np.ndarray], root=None) -> dict[int, np.ndarray]:
    """T_world_k by composing relative poses T_i_j (j into i) along a BFS tree from root
    (default: the largest connected set)."""
    if root is None:
        root = main_root(n, list(rel))
    reach, parent = largest_component(n, list(rel), root)
    T = {root: np.eye(4)}
    order = sorted(reach - {root}, key=lambda k: _depth(parent, k))
    for k in order:
        p = parent[k]
        if (p, k) in rel:
            T[k] = T[p] @ rel[(p, k)]
        else:
            T[k] = T[p] @ np.linalg.inv(rel[(k, p)])
    return T


def _depth(parent, k):
    d = 0
    while parent[k] is not None:
        k = parent[k]
        d += 1
    return d
