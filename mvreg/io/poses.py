"""Pose files: ``mvreg.poses/1`` JSON, TUM and KITTI text. Full float64 precision.

Every pose maps local (scan / patch) coordinates to world: ``T_world_local``.

``mvreg.poses/1``::

    {"format": "mvreg.poses/1",
     "poses": {"scan_000.ply": [[r00, r01, r02, tx], ..., [0, 0, 0, 1]], ...},
     ...any extra keys (units, solver stats, certificate)...}

TUM: one line per pose ``timestamp tx ty tz qx qy qz qw`` (timestamp = index unless
given). KITTI: one line per pose, the first 3 rows of the 4x4 matrix, row-major.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from mvreg.errors import InputError
from mvreg.io.atomic import atomic_write_json, atomic_write_text

POSES_FORMAT = "mvreg.poses/1"


def poses_to_json_dict(T_world_local: dict[str, np.ndarray], **extra) -> dict:
    """Build the ``mvreg.poses/1`` dictionary (poses as nested lists)."""
    out = {"format": POSES_FORMAT, "poses": {}}
    for name, t in T_world_local.items():
        out["poses"][str(name)] = np.asarray(t, dtype=np.float64).tolist()
    out.update(extra)
    return out


def write_poses_json(path: str | os.PathLike, T_world_local: dict[str, np.ndarray], **extra):
    """Write ``mvreg.poses/1`` atomically."""
    atomic_write_json(path, poses_to_json_dict(T_world_local, **extra))


def pose_with_offset(T_world_scan: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """The same pose between frames moved by ``offset`` (3,): ``S(offset) T S(-offset)``.

    If ``T_world_scan`` (4, 4) maps points ``p - offset`` of a scan to ``w - offset`` of the
    world (both shifted into a local frame), the result maps ``p`` to ``w``: the rotation is
    kept, the translation becomes ``t + offset - R offset``. ``-offset`` goes the other way.
    """
    T = np.asarray(T_world_scan, dtype=np.float64)
    o = np.asarray(offset, dtype=np.float64).reshape(3)
    out = T.copy()
    out[:3, 3] = T[:3, 3] + (o - T[:3, :3] @ o)
    return out


def check_pose(a, where: str, dim: int | None = 3) -> np.ndarray:
    """A rigid pose as a (d+1, d+1) float64 array, or InputError naming ``where``.

    Checks: square 4x4 (``dim=3``), 3x3 (``dim=2``) or either (``dim=None``); finite;
    last row ``[0, ..., 0, 1]``; rotation orthonormal (``|R^T R - I| < 1e-6``) with
    determinant +1.
    """
    try:
        a = np.asarray(a, dtype=np.float64)
    except (ValueError, TypeError):
        raise InputError(f"{where} is not a matrix of numbers") from None
    sizes = (3, 4) if dim is None else (dim + 1,)
    if a.ndim != 2 or a.shape[0] != a.shape[1] or a.shape[0] not in sizes:
        want = " or ".join(f"{k}x{k}" for k in sizes)
        raise InputError(f"{where} is not a {want} matrix (shape {a.shape})")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{where} has NaN or inf")
    d = a.shape[0] - 1
    if not np.array_equal(a[d], np.eye(d + 1)[d]):
        raise InputError(f"{where} has last row {a[d].tolist()}, not {np.eye(d + 1)[d].tolist()}")
    r = a[:d, :d]
    dev = float(np.max(np.abs(r.T @ r - np.eye(d))))
    if dev > 1e-6:
        raise InputError(
            f"{where} is not rigid: its rotation is not orthonormal (|R^T R - I| = {dev:.3g})"
        )
    if np.linalg.det(r) < 0:
        raise InputError(f"{where} is a reflection (det R = -1), not a rotation")
    return a


def read_poses_json(path: str | os.PathLike, dim: int | None = 3) -> dict[str, np.ndarray]:
    """Read the poses of an ``mvreg.poses/1`` file as {name: (d+1, d+1) float64}.

    Every pose is checked by :func:`check_pose` (``dim=3``: 4x4, ``dim=2``: 3x3,
    ``None``: either, the same for all). Raises InputError naming the file and the pose.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        dangling = path.is_symlink()
        why = "dangling symbolic link" if dangling else "no such file"
        raise InputError(f"{path}: {why}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(f"{path}: not a readable JSON file ({e})") from None
    except RecursionError:
        raise InputError(f"{path}: JSON nested too deeply") from None
    if not isinstance(data, dict) or data.get("format") != POSES_FORMAT:
        found = data.get("format") if isinstance(data, dict) else None
        why = "missing 'format'" if found is None else f"its 'format' is {str(found)[:60]!r}"
        raise InputError(f"{path}: not an {POSES_FORMAT} file ({why})")
    raw = data.get("poses", {})
    if not isinstance(raw, dict):
        raise InputError(f"{path}: 'poses' is not an object of name -> matrix")
    poses = {}
    for name, m in raw.items():
        poses[name] = check_pose(m, f"{path}: pose '{name}'", dim)
    if not poses:
        raise InputError(f"{path}: no poses")
    first = next(iter(poses))
    for name, a in poses.items():
        if a.shape != poses[first].shape:
            k, j = a.shape[0], poses[first].shape[0]
            raise InputError(
                f"{path}: pose '{name}' is {k}x{k} but pose '{first}' is {j}x{j} (mixed sizes)"
            )
    return poses


def _fmt(x: float) -> str:
    return repr(float(x))


def write_poses_tum(path, T_world_local: list[np.ndarray], timestamps=None) -> None:
    """TUM trajectory format (3D poses only)."""
    lines = []
    for i, t in enumerate(T_world_local):
        ts = float(i if timestamps is None else timestamps[i])
        q = Rotation.from_matrix(t[:3, :3]).as_quat()  # x, y, z, w
        vals = [ts, *t[:3, 3], *q]
        lines.append(" ".join(_fmt(v) for v in vals))
    atomic_write_text(path, "\n".join(lines) + "\n")


def read_poses_tum(path) -> tuple[np.ndarray, list[np.ndarray]]:
    rows = np.loadtxt(path, ndmin=2)
    poses = []
    for r in rows:
        t = np.eye(4)
        t[:3, :3] = Rotation.from_quat(r[4:8]).as_matrix()
        t[:3, 3] = r[1:4]
        poses.append(t)
    return rows[:, 0], poses


def write_poses_kitti(path, T_world_local: list[np.ndarray]) -> None:
    """KITTI odometry format: 12 numbers per line (3x4, row-major)."""
    lines = [" ".join(_fmt(v) for v in np.asarray(t)[:3, :4].ravel()) for t in T_world_local]
    atomic_write_text(path, "\n".join(lines) + "\n")


def read_poses_kitti(path) -> list[np.ndarray]:
    rows = np.loadtxt(path, ndmin=2)
    out = []
    for r in rows:
        t = np.eye(4)
        t[:3, :4] = r.reshape(3, 4)
        out.append(t)
    return out
