"""Local probes of one scan's pose against a model of the other scans (used by
:mod:`mvreg.globalstage.verify` and :mod:`mvreg.globalstage.place`).

* :func:`degenerate_direction`: the degree of freedom the model does not fix (the weakest
  direction of the scan's point-to-plane normal matrix against it, confirmed by ICP
  started a few voxels along it that does not come back and lands on a fit as good), or
  None;
* :func:`on_one_plane`: what a fit on one plane of the model leaves open (a scan fitting
  the others on ground alone), or None;
* :func:`unsettled`: why the pose is not a fixed point of point-to-plane ICP against the
  model (it moves to a clearly better fit), or "";
* :func:`relative_residual_outliers`: the verified scans that fit the others clearly worse
  than the other verified scans do (the pairs' relative residual rule, scan by scan);
* :func:`resting_on_undetermined`: the verified scans whose pairs link them only to
  undetermined scans;
* :func:`outnumbered_by_turns`: every verified scan, when more scans have a turned second
  pose as good than scans are verified.

Pure functions on world points, normals and a
:class:`~mvreg.globalstage.scan_model.ScanModel`; thresholds from the data (feature
voxel, the scans' noise) and the pairwise acceptance rule.
"""

from __future__ import annotations

import numpy as np

from mvreg.config.align import AlignConfig
from mvreg.geometry import rotation_from_vector, transform_points
from mvreg.globalstage.scan_model import (
    ScanModel,
    equally_good,
    model_fit,
    normal_matrix,
    overlap_spread,
)
from mvreg.pairwise.icp import icp_point_to_plane
from mvreg.pairwise.scoring import OFF_PLANE_MATCHES, off_plane_matches


def _describe(e: np.ndarray, c: np.ndarray, L: float) -> str:
    """Name the motion of the 6-vector ``e`` (rotation part scaled by 1/L)."""
    w, t = e[:3], e[3:]
    # A rotation about an axis far from the points moves them almost uniformly; call it a
    # rotation when its axis passes within about 5 rms radii of them (|w| >= 0.2 |e|).
    if np.linalg.norm(w) >= 0.2 * np.linalg.norm(e):
        axis = w / np.linalg.norm(w)
        # Rotation w/L about c plus translation t: the axis passes where the motion of
        # points is along it: point = c + (axis x t) * L / |w| (closest approach).
        through = c + np.cross(w, t) * L / float(np.dot(w, w))
        return (
            f"rotation about axis ({axis[0]:.3f}, {axis[1]:.3f}, {axis[2]:.3f}) through "
            f"({through[0]:.4g}, {through[1]:.4g}, {through[2]:.4g})"
        )
    d = t / np.linalg.norm(t)
    return f"translation along ({d[0]:.3f}, {d[1]:.3f}, {d[2]:.3f})"


def _step(e: np.ndarray, distance: float, c: np.ndarray, L: float) -> np.ndarray:
    """World motion moving points about ``distance`` along the 6-vector ``e``."""
    e = e / np.linalg.norm(e)
    S = np.eye(4)
    S[:3, :3] = rotation_from_vector(e[:3] * distance / L)
    S[:3, 3] = c - S[:3, :3] @ c + e[3:] * distance
    return S


def degenerate_direction(
    model: ScanModel,
    pts: np.ndarray,
    nrm: np.ndarray,
    tight: np.ndarray,
    idx: np.ndarray,
    noise: float,
    voxel: float,
    acfg: AlignConfig,
    agree_voxels: float = 1.0,
    probe_voxels: float = 3.0,
    max_source: int = 3000,
) -> str | None:
    """The degree of freedom of the scan (world ``pts``, ``nrm``) against ``model`` that
    the data do not fix, or None (:mod:`mvreg.globalstage.verify`, "undetermined")."""
    if np.count_nonzero(tight) < acfg.min_correspondences:
        return None
    H, c, L = normal_matrix(pts[tight], model.normals[idx[tight]])
    lam, vec = np.linalg.eigh(H)
    gate = (noise / voxel) ** 2
    stride = max(1, int(np.ceil(len(pts) / max_source)))
    src, src_n = pts[::stride], nrm[::stride]
    base_overlap, base_ratio, base_tight, _, _ = model_fit(model, src, src_n, noise, voxel, acfg)
    for k in range(6):
        if lam[k] >= gate:
            break
        e = vec[:, k]
        for sign in (1.0, -1.0):
            start = _step(sign * e, probe_voxels * voxel, c, L)
            T = icp_point_to_plane(
                src, src_n, model.points, model.normals, model.tree, start,
                (probe_voxels + 1.0) * voxel, 50, acfg.icp_min_normal_cos,
            )  # fmt: skip
            moved = float(np.median(np.linalg.norm(transform_points(T, src) - src, axis=1)))
            if moved <= agree_voxels * voxel:
                continue  # came back: this direction is fixed by the data
            q, qn = transform_points(T, src), src_n @ T[:3, :3].T
            overlap, ratio, tight2, _, _ = model_fit(model, q, qn, noise, voxel, acfg)
            if equally_good(overlap, ratio, base_overlap, base_ratio, len(src), acfg):
                return _describe(e, c, L)
    return None


def on_one_plane(
    model: ScanModel,
    pts: np.ndarray,
    nrm: np.ndarray,
    tight: np.ndarray,
    idx: np.ndarray,
    voxel: float,
    min_count: int = OFF_PLANE_MATCHES,
) -> str | None:
    """What a fit on one plane leaves open, or None: when fewer than ``min_count`` of
    the scan's ``tight`` matches to ``model`` (world ``pts``, ``nrm``; ``idx`` into the
    model) lie off the plane most of them share
    (:func:`mvreg.pairwise.scoring.off_plane_matches`), the scan fits the model on that
    plane (or parallel ones) alone: its heading about the normal and its slide along the
    plane are held by nothing but the noise of the normals.

    :func:`degenerate_direction` misses this: the normals' noise lifts the plane's
    eigenvalues above its gate, and probing, ICP slides many voxels on the noisy normals
    into a fit of other parts that reads worse. Scene of 60 LiDAR stations: five
    stations 41.6-115 deg off fitted the others on ground alone."""
    got = off_plane_matches(
        pts[tight], nrm[tight], model.normals[idx[tight]], voxel, min_count
    )  # fmt: skip
    if got is None:
        return None
    off, n, axis = got
    if off >= min_count:
        return None
    a = axis * np.sign(axis[np.argmax(np.abs(axis))])
    return (
        f"heading about ({a[0]:.3f}, {a[1]:.3f}, {a[2]:.3f}) and slide across it: only {off} "
        f"of its {n} close matches lie off one plane normal to it"
    )


def unsettled(
    model: ScanModel,
    pts: np.ndarray,
    nrm: np.ndarray,
    noise: float,
    voxel: float,
    acfg: AlignConfig,
    agree_voxels: float = 1.0,
    max_source: int = 3000,
) -> str:
    """Why the scan (world ``pts``, ``nrm``) is not at rest against ``model``, or "": a
    right pose is a fixed point of point-to-plane ICP against the other scans. When ICP
    from it moves the scan's points by more than ``agree_voxels`` feature voxels (median)
    to a clearly better fit (overlap share higher by more than three binomial standard
    errors, residual no higher), the pose is not the one the data hold (a scan placed by
    a single weak pair and not refined to the rest)."""
    stride = max(1, int(np.ceil(len(pts) / max_source)))
    src, src_n = pts[::stride], nrm[::stride]
    overlap0, ratio0, _, _, _ = model_fit(model, src, src_n, noise, voxel, acfg)
    T = icp_point_to_plane(
        src, src_n, model.points, model.normals, model.tree, np.eye(4),
        2.0 * voxel, 50, acfg.icp_min_normal_cos,
    )  # fmt: skip
    moved = float(np.median(np.linalg.norm(transform_points(T, src) - src, axis=1)))
    if moved <= agree_voxels * voxel:
        return ""
    q, qn = transform_points(T, src), src_n @ T[:3, :3].T
    overlap, ratio, _, _, _ = model_fit(model, q, qn, noise, voxel, acfg)
    spread = overlap_spread(overlap0, len(src))
    if overlap > overlap0 + spread and ratio <= ratio0:
        angle = np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1) / 2, -1, 1)))
        return (
            f"not at rest against the other scans: ICP moves it {moved / voxel:.1f} voxels "
            f"({angle:.1f} deg) to a better fit (overlap {overlap:.2f} vs {overlap0:.2f}, "
            f"residual {ratio:.1f}x vs {ratio0:.1f}x the noise)"
        )
    return ""


def relative_residual_outliers(out: dict, pre, acfg: AlignConfig) -> list[int]:
    """Mark ``unverified`` the verified scans whose residual against the model of the
    others is above ``relative_residual_factor`` times the median of the other verified
    scans' (at least two of them): the rule the pairs obey
    (:func:`mvreg.pairwise.align.reject_relative_outliers`), for a scan against the
    others, with a reference that leaves the scan itself out. A scan on a near-symmetric
    shape placed at a turned copy, confirmed by a cycle of two wrong pairs, fits the
    others worse than the right ones do (fuze sparse seed 1: 1.74x the noise against
    1.17 and 1.02; docs/design/verification.md). As for pairs, a median residual below
    ``relative_residual_floor_fine_voxels`` fine voxels (noise-free scans) passes.
    Decided for all scans against the same references; returns the scans marked."""
    factor = acfg.relative_residual_factor
    ratio = {
        s: v.model_residual_ratio
        for s, v in out.items()
        if v.status == "verified"
        and v.model_residual_ratio is not None
        and np.isfinite(v.model_residual_ratio)
    }
    if factor is None or len(ratio) < 3:
        return []
    marked = []
    for s, r in ratio.items():
        reference = float(np.median([x for k, x in ratio.items() if k != s]))
        fine_voxels = r * pre[s].noise / pre[s].fine_voxel_size
        if r > factor * reference and fine_voxels > acfg.relative_residual_floor_fine_voxels:
            marked.append(s)
            v = out[s]
            v.status, v.evidence = "unverified", ""
            v.reason = (
                f"residual against the other scans {r:.2f}x the noise, above {factor:g}x "
                f"the median of the other verified scans' ({reference:.2f})"
            )
    return marked


def resting_on_undetermined(out: dict, graph: dict, names) -> list[int]:
    """Mark ``undetermined`` the verified scans whose agreeing pairs (``graph``: {scan:
    partners}) all link them to undetermined scans: what the pairs confirm is the pose
    relative to those scans, and where their pose is open, so is this one's (cycloidal
    dense seed 1, with searched pairs: two scans confirmed only by cycles through scans a
    turn leaves open, 9.4 deg apart). Decided on the statuses before any is marked; scans
    verified by the model alone (no agreeing pair) are not affected. Not caught: a group
    of verified scans that confirm each other and reach the rest only through open scans.
    Returns the scans marked, in order."""
    open_ = {s for s, v in out.items() if v.status == "undetermined"}
    marked = [
        s
        for s, v in sorted(out.items())
        if v.status == "verified" and graph.get(s) and graph[s] <= open_
    ]
    for s in marked:
        v, partners = out[s], ", ".join(names[k] for k in sorted(graph[s]))
        v.status, v.evidence, v.degenerate_dof = "undetermined", "", f"that of {partners}"
        v.reason = f"its pairs link it only to scans whose pose is undetermined ({partners})"
    return marked


def outnumbered_by_turns(out: dict) -> list[int]:
    """Mark ``undetermined`` every verified scan when more scans have a distant second pose
    that fits as well (``degenerate_dof`` "a discrete turn ...":
    :func:`mvreg.globalstage.verify.search_alternatives`) than scans are verified.

    Most views then show the object near-symmetric, and on a near-symmetric object a pair's
    hypotheses come one per copy: a cycle closes on any choice of copies (for an exact
    symmetry, any choice per scan closes every cycle), so a cycle among the minority does
    not tell which copy each of its scans took, and the model of the others, made mostly of
    scans whose copy is open, cannot either (quadknot dense seed 2: three scans verified by
    their triangle of pairs, 60-180 deg off each other, among seven with a turned second
    pose). Returns the scans marked, in order."""
    turned = [
        s
        for s, v in out.items()
        if v.status == "undetermined" and (v.degenerate_dof or "").startswith("a discrete turn")
    ]
    marked = sorted(s for s, v in out.items() if v.status == "verified")
    if not marked or len(turned) <= len(marked):
        return []
    for s in marked:
        v = out[s]
        v.status, v.evidence = "undetermined", ""
        v.degenerate_dof = "which copy of a near-symmetric object it lies on"
        v.reason = (
            f"{len(turned)} of the {len(out)} scans have a second pose as good, turned "
            f"(only {len(marked)} verified): the object is near-symmetric as seen, and the "
            "pairs that verify this scan may all have taken the same turned copy"
        )
    return marked


def resting_on_open_partners(out: dict, names) -> list[int]:
    """On the final statuses (after every search, drop and placement): mark the verified
    scans that still rest on partners whose poses are not verified, until none changes.

    A verified scan's ``agreeing_pairs`` are what confirm it relative to the rest. When
    none of those partners ended verified and at least one is ``undetermined``, the scan
    is ``undetermined`` too (:func:`resting_on_undetermined`: what the pairs fix is the
    pose relative to scans whose pose is open). When none ended verified or undetermined
    (dropped, or placed elsewhere) and its evidence was a cycle, that cycle no longer
    exists: ``unverified``. Scans verified by the model check keep that evidence unless
    their partners are open. Cycloidal dense seed 0 with searched pairs: the search
    marked seven scans undetermined after the last check, and two scans verified through
    them stayed "verified", 123 deg apart. ``out``: {scan: ScanVerification}, changed in
    place. Returns the scans marked, in order."""
    index = {n: k for k, n in enumerate(names)}
    marked: list[int] = []
    while True:
        status = {s: v.status for s, v in out.items()}
        step = []
        for s, v in sorted(out.items()):
            partners = [index[n] for n in v.agreeing_pairs if n in index]
            if v.status != "verified" or not partners:
                continue
            states = {status.get(k, "unregistered") for k in partners}
            if "verified" in states or ("undetermined" not in states and v.evidence != "cycle"):
                continue
            step.append((s, "undetermined" in states, partners))
        for s, open_, partners in step:
            v, listed = out[s], ", ".join(names[k] for k in partners)
            v.evidence = ""
            if open_:
                v.status, v.degenerate_dof = "undetermined", f"that of {listed}"
                v.reason = f"its pairs link it only to scans whose pose is not verified ({listed})"
            else:
                v.status = "unverified"
                v.reason = f"the scans its pairs agree with ({listed}) have no verified pose"
        marked += [s for s, *_ in step]
        if not step:
            return marked
