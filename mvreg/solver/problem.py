"""PatchProblem: the input of the global stage (DESIGN.md section 1).

M patches (scans), N nodes (physical points). Observation l says: patch ``patch[l]``
sees node ``node[l]`` at local coordinates ``coords[l]`` with weight ``weight[l]``.
The unknowns are rotations R_i, translations t_i and node positions z_k with
``z_k ~ R_i x_ki + t_i`` (world_from_local).
"""

from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from mvreg.errors import DisconnectedError, IllPosedError, InputError, ProblemError

#: Largest magnitude of a coordinate: beyond it products of squares (the solvers' matrices
#: and their products) could overflow float64.
MAX_ABS_COORDINATE = 1e30
_MAX_INDEX = 2**62


def _as_real_array(a, name: str) -> np.ndarray:
    """``a`` as float64; ProblemError for complex, text or object data (never truncated)."""
    a = np.asarray(a)
    if a.dtype.kind not in "fiub":
        raise ProblemError(f"'{name}' must hold real numbers, got dtype {a.dtype}")
    return a.astype(np.float64, copy=False)


def _as_index_array(a, name: str) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 1:
        raise ProblemError(f"'{name}' must be a 1-D array, got shape {a.shape}")
    if a.dtype.kind == "f":
        if not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
            raise ProblemError(f"'{name}' must hold integers, found non-integer values")
        if a.size and np.max(np.abs(a)) >= _MAX_INDEX:
            raise ProblemError(f"'{name}' has an index too large ({np.max(np.abs(a)):.3g})")
        a = a.astype(np.int64)
    elif a.dtype.kind == "u" and a.size and a.max() >= _MAX_INDEX:
        raise ProblemError(f"'{name}' has an index too large ({a.max()})")
    elif a.dtype.kind not in "iu":
        raise ProblemError(f"'{name}' must hold integers, got dtype {a.dtype}")
    a = a.astype(np.int64, copy=False)
    if a.size and a.min() < 0:
        bad = int(np.flatnonzero(a < 0)[0])
        raise ProblemError(f"'{name}' has a negative index ({a[bad]}) at observation {bad}")
    return a


def _check_coords(coords: np.ndarray, patch: np.ndarray, node: np.ndarray) -> None:
    """Every coordinate finite and small enough that its square cannot overflow."""
    bad = ~np.all(np.isfinite(coords), axis=1)
    if np.any(bad):
        i = int(np.flatnonzero(bad)[0])
        raise ProblemError(
            f"'coords' has {int(bad.sum())} rows with NaN or inf (first: observation {i}, "
            f"patch {patch[i]}, node {node[i]})"
        )
    big = float(np.max(np.abs(coords)))
    if big > MAX_ABS_COORDINATE:
        i = int(np.argmax(np.max(np.abs(coords), axis=1)))
        raise ProblemError(
            f"'coords' has a value of magnitude {big:.3g} (observation {i}): squares "
            f"overflow float64 beyond {MAX_ABS_COORDINATE:.0e}; rescale the coordinates"
        )


def _checked_weight(weight, k: int) -> np.ndarray:
    if weight is None:
        return np.ones(k)
    weight = _as_real_array(weight, "weight")
    if weight.shape != (k,):
        raise ProblemError(f"'weight' must have shape ({k},), got {weight.shape}")
    if not np.all(np.isfinite(weight)) or np.any(weight < 0):
        i = int(np.flatnonzero(~np.isfinite(weight) | (weight < 0))[0])
        raise ProblemError(f"'weight' must be finite and >= 0 (observation {i} has {weight[i]})")
    return weight


@dataclass
class PatchProblem:
    """Observations of shared nodes by patches, validated on construction.

    Args:
        coords: (K, d) float64 local coordinates, d in {2, 3}.
        patch: (K,) int patch index of each observation, 0 <= patch < M.
        node: (K,) int node id of each observation (any non-negative ids).
        weight: (K,) float >= 0, default 1.
        patch_names: M names (default "0", "1", ...).
        num_patches: M, default max(patch) + 1 (or len(patch_names)).
        check_well_posed: run the local well-posedness and connectivity checks.

    Raises:
        ProblemError (NaN/inf, bad indices, duplicate observations, empty patches),
        DisconnectedError (patch graph not connected), IllPosedError (a patch shares
        fewer than d+1 affinely independent nodes with the rest).
    """

    coords: np.ndarray
    patch: np.ndarray
    node: np.ndarray
    weight: np.ndarray | None = None
    patch_names: list[str] | None = None
    num_patches: int | None = None
    check_well_posed: bool = field(default=True, repr=False)

    def __post_init__(self):
        coords = _as_real_array(self.coords, "coords")
        if coords.ndim != 2 or coords.shape[1] not in (2, 3):
            raise ProblemError(f"'coords' must have shape (K, 2) or (K, 3), got {coords.shape}")
        k = coords.shape[0]
        if k == 0:
            raise ProblemError("the problem has no observations")
        patch = _as_index_array(self.patch, "patch")
        node = _as_index_array(self.node, "node")
        if patch.shape[0] != k or node.shape[0] != k:
            raise ProblemError(
                f"'coords' has {k} rows but 'patch' has {patch.shape[0]} and 'node' {node.shape[0]}"
            )
        _check_coords(coords, patch, node)
        weight = _checked_weight(self.weight, k)
        m = self.num_patches
        if m is None:
            m = len(self.patch_names) if self.patch_names is not None else int(patch.max()) + 1
        m = int(m)
        if m > k:  # checked before anything is sized by m
            raise ProblemError(
                f"{m} patches (largest 'patch' index {int(patch.max())}) but only {k} "
                "observations: some patch would have no observations"
            )
        names = (
            [str(i) for i in range(m)]
            if self.patch_names is None
            else [str(s) for s in self.patch_names]
        )
        if len(names) != m:
            raise ProblemError(f"{len(names)} patch names given for {m} patches")
        if len(set(names)) != m:
            seen: set[str] = set()
            twice = next(n for n in names if n in seen or seen.add(n))
            raise ProblemError(f"'patch_names' are not unique ({twice!r} more than once)")
        if patch.max() >= m:
            i = int(np.flatnonzero(patch >= m)[0])
            source = (
                f"{len(names)} 'patch_names'"
                if self.patch_names is not None and self.num_patches is None
                else f"M = {m}"
            )
            raise ProblemError(
                f"'patch' index {patch[i]} at observation {i} is out of range ({source})"
            )
        # Compact node ids to 0..N-1 (the file may use any non-negative ids).
        node_ids, node_idx = np.unique(node, return_inverse=True)
        key = patch * len(node_ids) + node_idx
        uniq, counts = np.unique(key, return_counts=True)
        if np.any(counts > 1):
            dup = uniq[counts > 1][0]
            p, n = divmod(int(dup), len(node_ids))
            raise ProblemError(
                f"patch '{names[p]}' sees node {node_ids[n]} more than once "
                f"({int((counts > 1).sum())} duplicate (patch, node) pairs)"
            )
        seen = np.bincount(patch, minlength=m)
        if np.any(seen == 0):
            empty = [names[i] for i in np.flatnonzero(seen == 0)]
            raise ProblemError(
                f"{len(empty)} patch(es) have no observations: {', '.join(empty[:10])}"
                + (" ..." if len(empty) > 10 else "")
            )
        self.coords, self.patch, self.weight = coords, patch, weight
        self.node_ids = node_ids
        self.node_index = node_idx.astype(np.int64)
        self.patch_names = names
        self.num_patches = m
        if self.check_well_posed:
            self.check_connected()
            self.check_local_rigidity()

    # ------------------------------------------------------------------ basic facts
    @property
    def d(self) -> int:
        return int(self.coords.shape[1])

    @property
    def num_nodes(self) -> int:
        return int(self.node_ids.shape[0])

    @property
    def num_observations(self) -> int:
        return int(self.coords.shape[0])

    def __repr__(self) -> str:
        return (
            f"PatchProblem(d={self.d}, patches={self.num_patches}, nodes={self.num_nodes}, "
            f"observations={self.num_observations})"
        )

    def shared_mask(self) -> np.ndarray:
        """(K,) bool: observation has weight > 0 and its node is seen (w > 0) by >= 2 patches."""
        pos = self.weight > 0
        seen = np.bincount(self.node_index[pos], minlength=self.num_nodes)
        return pos & (seen[self.node_index] >= 2)

    # ------------------------------------------------------------------ structure
    def components(self) -> list[np.ndarray]:
        """Connected components of the patch graph (patches sharing a weighted node).

        Returns a list of arrays of patch indices, largest first.
        """
        m, n = self.num_patches, self.num_nodes
        mask = self.shared_mask()
        inc = sp.coo_matrix(
            (np.ones(int(mask.sum())), (self.patch[mask], m + self.node_index[mask])),
            shape=(m + n, m + n),
        )
        _, labels = connected_components(inc, directed=False)
        labels = labels[:m]
        comps = [np.flatnonzero(labels == c) for c in np.unique(labels)]
        comps.sort(key=lambda c: (-len(c), c[0]))
        return comps

    def check_connected(self) -> None:
        comps = self.components()
        if len(comps) > 1:
            raise DisconnectedError([[self.patch_names[i] for i in c] for c in comps])

    def check_local_rigidity(self) -> None:
        """Each patch must share >= d+1 affinely independent nodes with the others.

        This is necessary for nullity(C) = d (paper 000 section 2.4): otherwise the
        patch's rotation is not determined. The global test (lambda_{d+1}(C) ~ 0) is
        done by the solver.
        """
        bad = self.underdetermined_patches()
        if bad:
            names = [self.patch_names[i] for i in bad]
            raise IllPosedError(
                f"ill-posed: {len(bad)} patch(es) share fewer than {self.d + 1} affinely "
                f"independent nodes with the others, so their rotation is not determined: "
                + ", ".join(names[:10])
                + (" ..." if len(names) > 10 else ""),
                names,
            )

    def underdetermined_patches(self) -> list[int]:
        d, m = self.d, self.num_patches
        mask = self.shared_mask()
        p, x, w = self.patch[mask], self.coords[mask], self.weight[mask]
        counts = np.bincount(p, minlength=m)
        bad = set(np.flatnonzero(counts < d + 1).tolist())
        # Affine rank: smallest singular value of the weighted, centred coordinates.
        order = np.argsort(p, kind="stable")
        p, x, w = p[order], x[order], w[order]
        sw = np.bincount(p, weights=w, minlength=m)
        cen = np.stack([np.bincount(p, weights=w * x[:, a], minlength=m) for a in range(d)], 1)
        cen /= np.maximum(sw, 1e-300)[:, None]
        xc = (x - cen[p]) * np.sqrt(w)[:, None]
        cov = np.zeros((m, d, d))
        for a in range(d):
            for b in range(a, d):
                cov[:, a, b] = cov[:, b, a] = np.bincount(
                    p, weights=xc[:, a] * xc[:, b], minlength=m
                )
        ev = np.linalg.eigvalsh(cov)
        flat = ev[:, 0] <= 1e-12 * np.maximum(ev[:, -1], 1e-300)
        bad.update(np.flatnonzero(flat & (counts >= d + 1)).tolist())
        return sorted(bad)

    def subproblem(self, patches) -> PatchProblem:
        """The problem restricted to the given patch indices (renumbered in that order)."""
        patches = np.asarray(patches, dtype=np.int64)
        remap = -np.ones(self.num_patches, dtype=np.int64)
        remap[patches] = np.arange(len(patches))
        keep = remap[self.patch] >= 0
        return PatchProblem(
            coords=self.coords[keep],
            patch=remap[self.patch[keep]],
            node=self.node_ids[self.node_index[keep]],
            weight=self.weight[keep],
            patch_names=[self.patch_names[i] for i in patches],
            num_patches=len(patches),
            check_well_posed=self.check_well_posed,
        )

    def with_weights(self, weight: np.ndarray) -> PatchProblem:
        return PatchProblem(
            self.coords,
            self.patch,
            self.node_ids[self.node_index],
            weight,
            self.patch_names,
            self.num_patches,
            self.check_well_posed,
        )


# ---------------------------------------------------------------------- .npz files
def save_problem(path: str | os.PathLike, problem: PatchProblem) -> None:
    """Write a problem as .npz with arrays coords, patch, node, weight, patch_names."""
    import io

    from mvreg.io.atomic import atomic_write_bytes

    buf = io.BytesIO()
    np.savez_compressed(
        buf,
        coords=problem.coords,
        patch=problem.patch,
        node=problem.node_ids[problem.node_index],
        weight=problem.weight,
        patch_names=np.asarray(problem.patch_names, dtype=str),
    )
    atomic_write_bytes(path, buf.getvalue())


def load_problem(path: str | os.PathLike, check_well_posed: bool = True) -> PatchProblem:
    """Read a problem .npz (arrays coords, patch, node, optional weight, patch_names).

    Raises InputError naming the file for unreadable files and ProblemError (prefixed with
    the file name) for invalid content.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file")
    if not zipfile.is_zipfile(path):
        raise InputError(f"{path}: not an .npz file (not a zip archive)")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise InputError(f"{path}: not a readable .npz file ({e})") from None
    missing = [k for k in ("coords", "patch", "node") if k not in arrays]
    if missing:
        raise InputError(f"{path}: missing array(s) {', '.join(missing)}")
    names = arrays.get("patch_names")
    try:
        return PatchProblem(
            coords=arrays["coords"],
            patch=arrays["patch"],
            node=arrays["node"],
            weight=arrays.get("weight"),
            patch_names=None if names is None else [str(s) for s in names.tolist()],
            check_well_posed=check_well_posed,
        )
    except ProblemError as e:
        e.args = (f"{path}: {e.args[0]}",)
        raise
