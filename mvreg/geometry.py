"""Small rigid-geometry helpers shared by every stage.

Convention everywhere: ``p_world = R_world_local @ p_local + t_world_local``; a 4x4
``T_world_local`` holds ``[R t; 0 1]``.
"""

from __future__ import annotations

import math

import numpy as np


def project_to_orthogonal(blocks: np.ndarray, allow_reflections: bool = False) -> np.ndarray:
    """Nearest orthogonal (or special orthogonal) matrix of each block, by SVD.

    Args:
        blocks: (..., d, d) float64.
        allow_reflections: if False, the result is in SO(d) (det = +1).
    Returns:
        (..., d, d) float64.
    """
    u, _, vt = np.linalg.svd(blocks)
    r = u @ vt
    if not allow_reflections:
        det = np.linalg.det(r)
        flip = det < 0
        if np.any(flip):
            u = u.copy()
            u[flip, :, -1] *= -1.0
            r = u @ vt
    return r


def make_transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(d, d), (d,) -> (d+1, d+1) homogeneous transform."""
    d = rotation.shape[0]
    t = np.eye(d + 1)
    t[:d, :d] = rotation
    t[:d, d] = translation
    return t


def invert_transform(t: np.ndarray) -> np.ndarray:
    """Inverse of a rigid (d+1, d+1) transform."""
    d = t.shape[0] - 1
    r = t[:d, :d]
    out = np.eye(d + 1)
    out[:d, :d] = r.T
    out[:d, d] = -r.T @ t[:d, d]
    return out


def transform_points(t: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a (d+1, d+1) transform to (N, d) points."""
    d = t.shape[0] - 1
    return points @ t[:d, :d].T + t[:d, d]


def random_rotations(rng: np.random.Generator, n: int, d: int = 3) -> np.ndarray:
    """(n, d, d) rotations drawn uniformly (Haar) from SO(d)."""
    g = rng.standard_normal((n, d, d))
    q, r = np.linalg.qr(g)
    q = q * np.sign(np.diagonal(r, axis1=1, axis2=2))[:, None, :]
    det = np.linalg.det(q)
    q[det < 0, :, 0] *= -1.0
    return q


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross(a, b)`` of (N, 3) arrays, value for value (the same products and
    differences in the same order), without its axis handling: ICP calls it on small
    arrays hundreds of thousands of times per run."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    np.subtract(a1 * b2, a2 * b1, out=out[..., 0])
    np.subtract(a2 * b0, a0 * b2, out=out[..., 1])
    np.subtract(a0 * b1, a1 * b0, out=out[..., 2])
    return out


def norm2(x: np.ndarray) -> float:
    """``np.linalg.norm(x)`` (2-norm of the flattened array), value for value, without its
    dispatch (called a few times per ICP iteration)."""
    x = x.ravel()
    return math.sqrt(float(np.dot(x, x)))


def rotation_from_vector(w: np.ndarray) -> np.ndarray:
    """(3, 3) rotation of the rotation vector ``w`` (axis times angle), by Rodrigues."""
    theta = float(np.sqrt(np.dot(w, w)))  # np.linalg.norm(w), without its dispatch
    k = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if theta < 1e-12:
        return np.eye(3) + k
    k /= theta
    return np.eye(3) + np.sin(theta) * k + (1 - np.cos(theta)) * (k @ k)


def rotation_angle_deg(r: np.ndarray) -> np.ndarray:
    """Geodesic angle (degrees) of rotation(s) (..., d, d), d = 2 or 3."""
    d = r.shape[-1]
    if d == 2:
        return np.degrees(np.abs(np.arctan2(r[..., 1, 0], r[..., 0, 0])))
    tr = np.trace(r, axis1=-2, axis2=-1)
    # arccos is ill-conditioned near 0: use the robust atan2 form on the skew part.
    skew = np.stack(
        [r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]],
        axis=-1,
    )
    return np.degrees(np.arctan2(0.5 * np.linalg.norm(skew, axis=-1), 0.5 * (tr - 1.0)))
