"""Block helpers shared by the solvers.

X = O^T is (n, d) with n = M d; block i is X_i = R_i^T (d x d). Rotations are (M, d, d)
R_world_patch. Pure functions of arrays; no state.
"""

from __future__ import annotations

import numpy as np

from mvreg.geometry import project_to_orthogonal


def x_from_rotations(R: np.ndarray) -> np.ndarray:
    """(M, d, d) R_world_patch -> X = O^T (n, d) with X_i = R_i^T."""
    m, d, _ = R.shape
    return R.transpose(0, 2, 1).reshape(m * d, d)


def rotations_from_x(X: np.ndarray, d: int) -> np.ndarray:
    """(n, d) X -> (M, d, d) blocks R_i = X_i^T (no projection)."""
    return X.reshape(-1, d, d).transpose(0, 2, 1)


def round_to_rotations(X: np.ndarray, d: int, allow_reflections: bool = False) -> np.ndarray:
    """Round an (n, d) factor (e.g. sqrt(M) U, or O^T) to rotations (M, d, d).

    A global reflection is a gauge: when most blocks have det < 0 the whole factor is
    reflected first, so that projecting onto SO(d) changes as few blocks as possible.
    """
    blocks = X.reshape(-1, d, d)
    if not allow_reflections:
        det = np.linalg.det(blocks)
        if np.sum(det < 0) > np.sum(det > 0):
            X = X.copy()
            X[:, -1] *= -1.0
            blocks = X.reshape(-1, d, d)
    xi = project_to_orthogonal(blocks, allow_reflections=allow_reflections)  # X_i
    return xi.transpose(0, 2, 1)


def feasible_x(R: np.ndarray, d: int, allow_reflections: bool = False) -> np.ndarray:
    """X = O^T (n, d) on the constraint set from any (M, d, d) start: blocks rounded to
    SO(d) / O(d) first (see round_to_rotations)."""
    return x_from_rotations(round_to_rotations(x_from_rotations(R), d, allow_reflections))


def project_blocks(Y: np.ndarray, d: int, allow_reflections: bool) -> tuple[np.ndarray, float]:
    """Blockwise X_i = argmax Tr(Q^T Y_i) over O(d) / SO(d) for Y (n, d), and the attained
    sum_i max Tr(Q^T Y_i). Q = U V^T from the SVD Y_i = U S V^T; for SO(d) the last
    singular direction's sign is flipped where det(U V^T) < 0."""
    blocks = Y.reshape(-1, d, d)
    u, s, vt = np.linalg.svd(blocks)
    if allow_reflections:
        q = u @ vt
        best = float(np.sum(s))
    else:
        sign = np.sign(np.linalg.det(u @ vt))
        sign[sign == 0] = 1.0
        u = u.copy()
        u[:, :, -1] *= sign[:, None]
        q = u @ vt
        s = s.copy()
        s[:, -1] *= sign
        best = float(np.sum(s))
    return q.reshape(-1, d), best


def sym(a: np.ndarray) -> np.ndarray:
    return 0.5 * (a + np.swapaxes(a, -1, -2))


def skew(a: np.ndarray) -> np.ndarray:
    return 0.5 * (a - np.swapaxes(a, -1, -2))


def diag_blocks_of_gram(U: np.ndarray, s: np.ndarray, d: int) -> np.ndarray:
    """Diagonal d x d blocks of U diag(s) U^T for U (n, r): returns (M, d, d)."""
    ub = U.reshape(-1, d, U.shape[1])
    return np.einsum("mar,r,mbr->mab", ub, s, ub)


def block_apply(blocks: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Apply a block-diagonal matrix given as (M, d, d) blocks to V (n, r)."""
    m, d, _ = blocks.shape
    return np.einsum("mab,mbr->mar", blocks, V.reshape(m, d, -1)).reshape(m * d, -1)


def diag_blocks_of_cg(U: np.ndarray, s: np.ndarray, CU: np.ndarray, d: int) -> np.ndarray:
    """Diagonal d x d blocks of C G for G = U diag(s) U^T, given CU = C U: (M, d, d)."""
    r = U.shape[1]
    return np.einsum("mar,r,mbr->mab", CU.reshape(-1, d, r), s, U.reshape(-1, d, r))
