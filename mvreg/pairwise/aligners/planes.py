"""``planes``: align two scans of a machined part from their plane faces, no features.

Where FPFH + RANSAC fails on sparse scans of machined parts (few points per face, the
same descriptor on every flat patch), the faces themselves still say a lot: two
non-parallel faces seen by both scans fix the rotation, and their offsets fix the
translation across their line of intersection.

Per scan (:meth:`PlaneAligner.prepare`, cached on the scan): faces grown on the
feature-level points (:func:`plane_faces`): neighbours joined when their normals agree
within ``FACE_ANGLE_DEG``; a region is a face when it holds at least ``MIN_FACE_SHARE`` of
the points (and ``MIN_FACE_POINTS``) and lies within ``FACE_FLATNESS_VOXELS`` of its plane
(rms); the normals are oriented (towards the sensor), so a face's normal has a sign.
Per pair (j onto i): every two faces of scan j at an angle of 30-150 deg against every two
faces of scan i at the same angle (within ``ANGLE_TOLERANCE_DEG``) give a rotation (the
normals and their cross product); the translation solves the two plane offsets, and
along the faces' common line puts the two face pairs' centroids level. The hypotheses
are ranked by how many of scan j's feature points they bring within
``ransac_distance_voxels`` of scan i's (their normals agreeing); the best
``ransac_hypotheses_tried`` distinct ones are verified as ``feature-ransac`` verifies its
own (:meth:`~mvreg.pairwise.aligners.feature_ransac.FeatureRansacAligner`: ICP, the
acceptance rule, the best supported kept). Deterministic (no random choices; ``seed``
unused). Stats: ``faces`` (of each scan), ``hypotheses_drawn``, ``pose_hypotheses``.
What it achieves, measured: ``docs/design/pairwise.md``.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from mvreg.executor import single_threaded_blas
from mvreg.geometry import transform_points
from mvreg.pairwise.aligners.base import register_aligner
from mvreg.pairwise.aligners.feature_ransac import FeatureRansacAligner
from mvreg.pairwise.decision import choose
from mvreg.pairwise.icp import feature_level_tree
from mvreg.pairwise.result import PairResult, pair_result

FACE_ANGLE_DEG = 10.0
MIN_FACE_SHARE = 0.02
MIN_FACE_POINTS = 12
FACE_FLATNESS_VOXELS = 0.35
MAX_FACES = 10
ANGLE_TOLERANCE_DEG = 8.0
NEIGHBOURS = 8


def plane_faces(points: np.ndarray, normals: np.ndarray, voxel: float) -> list[dict]:
    """Flat faces of a scan, largest first: ``normal`` (oriented as the points'),
    ``offset`` (n . x + offset = 0), ``centroid``, ``count``."""
    n = len(points)
    if n < MIN_FACE_POINTS:
        return []
    k = min(NEIGHBOURS + 1, n)
    dist, idx = cKDTree(points).query(points, k=k)
    rows = np.repeat(np.arange(n), k - 1)
    cols = idx[:, 1:].ravel()
    near = dist[:, 1:].ravel() <= 2.5 * voxel
    agree = np.einsum("ij,ij->i", normals[rows], normals[cols]) >= np.cos(
        np.radians(FACE_ANGLE_DEG)
    )
    keep = near & agree
    graph = sp.coo_matrix((np.ones(int(keep.sum())), (rows[keep], cols[keep])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    sizes = np.bincount(label)
    faces = []
    for lab in np.argsort(-sizes, kind="stable"):
        if sizes[lab] < max(MIN_FACE_POINTS, MIN_FACE_SHARE * n) or len(faces) >= MAX_FACES:
            break
        P = points[label == lab]
        c = P.mean(0)
        _, _, vt = np.linalg.svd(P - c, full_matrices=False)
        normal = vt[2] if vt[2] @ normals[label == lab].sum(0) >= 0 else -vt[2]
        if np.sqrt(np.mean(((P - c) @ normal) ** 2)) > FACE_FLATNESS_VOXELS * voxel:
            continue  # a curved region, not a face
        faces.append({"normal": normal, "offset": -float(normal @ c), "centroid": c,
                      "count": int(sizes[lab])})  # fmt: skip
    return faces


def _frame(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Orthonormal frame (columns) from two non-parallel unit vectors."""
    e1 = a
    e2 = b - (b @ a) * a
    e2 /= np.linalg.norm(e2)
    return np.stack([e1, e2, np.cross(e1, e2)], axis=1)


def _pose(fa, fb, fp, fq) -> np.ndarray:
    """T_i_j putting faces (fa, fb) of scan j onto faces (fp, fq) of scan i."""
    R = _frame(fp["normal"], fq["normal"]) @ _frame(fa["normal"], fb["normal"]).T
    u, v = fp["normal"], fq["normal"]
    w = np.cross(u, v)
    w /= np.linalg.norm(w)
    # plane offsets: u . (R x + t) + d_p = 0 for x on face a (u . R x = -d_a)
    rhs = [fa["offset"] - fp["offset"], fb["offset"] - fq["offset"]]
    c_j = (
        R
        @ (fa["centroid"] * fa["count"] + fb["centroid"] * fb["count"])
        / (fa["count"] + fb["count"])
    )
    c_i = (fp["centroid"] * fp["count"] + fq["centroid"] * fq["count"]) / (
        fp["count"] + fq["count"]
    )
    A = np.stack([u, v, w])
    t = np.linalg.lstsq(A, np.array([*rhs, w @ (c_i - c_j)]), rcond=None)[0]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def face_hypotheses(faces_i: list[dict], faces_j: list[dict]) -> list[np.ndarray]:
    """Every pose putting two faces of scan j onto two of scan i at the same angle."""
    out = []
    tol = np.radians(ANGLE_TOLERANCE_DEG)
    for a in range(len(faces_j)):
        for b in range(len(faces_j)):
            if a == b:
                continue
            ang_j = np.arccos(np.clip(faces_j[a]["normal"] @ faces_j[b]["normal"], -1, 1))
            if not np.radians(30) <= ang_j <= np.radians(150):
                continue
            for p in range(len(faces_i)):
                for q in range(len(faces_i)):
                    if p == q:
                        continue
                    ang_i = np.arccos(np.clip(faces_i[p]["normal"] @ faces_i[q]["normal"], -1, 1))
                    if abs(ang_i - ang_j) <= tol:
                        out.append(_pose(faces_j[a], faces_j[b], faces_i[p], faces_i[q]))
    return out


def _rank(pre_i, pre_j, hypotheses, cfg, voxel) -> list[np.ndarray]:
    """Hypotheses by how many of scan j's feature points land on scan i (normals agreeing)."""
    tree = feature_level_tree(pre_i)
    dist = cfg.ransac_distance_voxels * voxel
    scores = []
    for T in hypotheses:
        d, nn = tree.query(transform_points(T, pre_j.points), distance_upper_bound=dist)
        ok = np.isfinite(d)
        agree = np.einsum("ij,ij->i", pre_i.normals[nn[ok]], pre_j.normals[ok] @ T[:3, :3].T)
        scores.append(int(np.count_nonzero(agree >= cfg.icp_min_normal_cos)))
    order = np.argsort(-np.asarray(scores), kind="stable")
    return [hypotheses[k] for k in order]


@register_aligner("planes")
class PlaneAligner(FeatureRansacAligner):
    """Face pairs as pose hypotheses, then ICP and the acceptance rule (module docstring)."""

    def prepare(self, pre) -> None:
        super().prepare(pre)
        for p in pre:
            self.faces(p)

    def faces(self, pre_s) -> list[dict]:
        """The scan's faces (cached on it; built in :meth:`prepare` before threads run)."""
        if "faces" not in pre_s._cache:
            pre_s._cache["faces"] = plane_faces(pre_s.points, pre_s.normals, pre_s.voxel_size)
        return pre_s._cache["faces"]

    def align(self, pre_i, pre_j, guess=None, seed=0, *, i=0, j=1) -> PairResult:
        start, scales, cfg = time.perf_counter(), self.scales_for(pre_i), self.cfg
        fi, fj = self.faces(pre_i), self.faces(pre_j)
        with single_threaded_blas():
            hyps = face_hypotheses(fi, fj)
            stats = {"faces": [len(fi), len(fj)], "hypotheses_drawn": len(hyps)}
            if not hyps:
                return pair_result(pre_i, pre_j, i, j, np.eye(4), "no two faces to match",
                                   None, stats, start, fine_voxel=scales.fine_voxel)  # fmt: skip
            ranked = _rank(pre_i, pre_j, hyps, cfg, scales.voxel)
            # the best verified, then the next ones screened, as feature-ransac does
            best = ranked[: 8 * cfg.ransac_hypotheses_tried]
            tried = self._verify_distinct(pre_i, pre_j, best, scales)
            stats["pose_hypotheses"] = [t.T for t in tried]
            T, reason, scores, stats["coarse"] = choose(tried, cfg, stats)
        return pair_result(
            pre_i, pre_j, i, j, T, reason, scores, stats, start, fine_voxel=scales.fine_voxel
        )
