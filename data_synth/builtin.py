"""The built-in default object: a procedural, clearly asymmetric closed surface.

A unit icosphere is displaced radially by
  - coarse detail: Gaussian bumps and dents at random directions (three horns, lobes,
    hollows that occlude each other), and
  - fine detail: a few dozen random plane waves of short wavelength (ridges and ripples),
then stretched along three different axes and bent, so that no rotation other than the
identity and no reflection maps it onto itself. Being a radial graph over the sphere it
stays a closed, manifold, outward-oriented surface. Everything is drawn from
``numpy.random.default_rng(seed)``: the same seed gives the same vertices bit for bit.
"""

from __future__ import annotations

import numpy as np
import trimesh

#: Largest bounding-box extent of the built-in object (unitless; think of it as metres).
BUILTIN_SIZE = 1.0


def builtin_object(seed: int = 0, subdivisions: int = 6) -> trimesh.Trimesh:
    """Procedural asymmetric object, deterministic from ``seed``.

    Args:
        seed: selects the shape; any integer >= 0 gives a different object.
        subdivisions: icosphere subdivisions (6 gives 40,962 vertices / 81,920 faces,
            enough to carry the fine detail; 4 is a quick coarse version).
    Returns:
        ``trimesh.Trimesh`` (not open3d), (V, 3) float64 vertices, (F, 3) int64 faces,
        watertight, centred on its bounding-box centre, largest extent ``BUILTIN_SIZE``.
    """
    if seed < 0:
        raise ValueError(f"builtin_object seed must be >= 0, not {seed}")
    rng = np.random.default_rng([seed, 0x5EED])
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    directions = np.asarray(sphere.vertices, dtype=np.float64)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)

    radius = 1.0 + _coarse_detail(rng, directions) + _fine_detail(rng, directions)
    radius = np.maximum(radius, 0.35)  # stays star-shaped, never folds through the centre
    vertices = directions * radius[:, None]
    vertices = _stretch_and_bend(rng, vertices)

    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    vertices = (vertices - 0.5 * (lo + hi)) * (BUILTIN_SIZE / float(np.max(hi - lo)))
    return trimesh.Trimesh(vertices, np.asarray(sphere.faces, dtype=np.int64), process=False)


def _random_directions(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.standard_normal((n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _coarse_detail(rng: np.random.Generator, directions: np.ndarray) -> np.ndarray:
    """Radial offset (V,) from Gaussian bumps and dents on the sphere.

    Three long horns of different lengths give the shape an unmistakable orientation,
    medium bumps make lobes, and dents make concavities (hence self-occlusion).
    """
    horns = (rng.uniform(0.7, 1.2, 3), rng.uniform(0.22, 0.32, 3))
    lobes = (rng.uniform(0.1, 0.35, 8), rng.uniform(0.3, 0.6, 8))
    dents = (-rng.uniform(0.15, 0.3, 3), rng.uniform(0.2, 0.35, 3))
    amplitudes = np.concatenate([horns[0], lobes[0], dents[0]])
    widths = np.concatenate([horns[1], lobes[1], dents[1]])  # angular sigma, radians
    centres = _random_directions(rng, len(amplitudes))
    cos_angle = np.einsum("ij,kj->ik", directions, centres)  # (V, K); einsum: no BLAS
    return np.sum(amplitudes * np.exp((cos_angle - 1.0) / widths**2), axis=1)


def _fine_detail(rng: np.random.Generator, directions: np.ndarray) -> np.ndarray:
    """Radial offset (V,) from short plane waves: ripples of ~1-2% of the object size."""
    n_waves = 24
    axes = _random_directions(rng, n_waves)
    frequencies = rng.uniform(10.0, 24.0, n_waves)  # radians per unit of u . axis
    phases = rng.uniform(0.0, 2.0 * np.pi, n_waves)
    amplitudes = rng.uniform(0.004, 0.012, n_waves)
    heights = np.einsum("ij,kj->ik", directions, axes)  # (V, n_waves)
    return np.einsum("ij,j->i", np.sin(heights * frequencies + phases), amplitudes)


def _stretch_and_bend(rng: np.random.Generator, vertices: np.ndarray) -> np.ndarray:
    """Distinct scale per axis, then a bend and a shear that break remaining mirror planes."""
    scales = np.array([1.0, rng.uniform(0.6, 0.7), rng.uniform(0.4, 0.5)])
    v = vertices * scales
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    bend = rng.uniform(0.25, 0.35)
    shear = rng.uniform(0.1, 0.2)
    return np.column_stack([x + shear * z, y + bend * x**2, z + 0.5 * bend * x * y])
