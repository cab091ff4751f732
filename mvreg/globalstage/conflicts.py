"""Contradictions between registered scans' views (free-space tests), and which side of
each one loses (:mod:`mvreg.globalstage.verify` runs them; why each rule:
docs/design/verification.md).

Two kinds of conflict:

* with a scan that shares close matches with this one: a free-space or unseen share above
  the pairwise limits loosened by ``coarse_gate_slack``. It counts against the scan whose
  own evidence is weaker; cycle evidence stands; equal evidence overrules neither.
* *gross*, with any scan, both views seen from their sensor: more than
  ``AlignConfig.max_free_space_apart`` of the facing points in the other scan's free
  space. Right poses read a few percent at most, surface
  shared or not (0.025 on opposite sides of an object; over the 88 generalization runs,
  no verified scan read more than 0.060 but one 66 deg off, at 0.982), so one of the two
  poses is wrong: it counts against the weaker side even against a cycle, then against
  the one the others cover less, and when they tie against both (leaving both verified
  would claim a pose that is wrong).
"""

from __future__ import annotations

import numpy as np

from mvreg.geometry import invert_transform
from mvreg.pairwise.scoring import (
    free_space_violation,
    seen_from_sensors,
    unseen_violation,
    view_conflicts,
)


def free_space_conflicts(v, s, others, support, pre, T_world_scan, names, acfg) -> list:
    """Both free-space tests of scan ``s`` against every scan of ``others`` (the largest
    values go into ``v``); the conflicts ``(k, why, gross)`` (module docstring)."""
    T = T_world_scan[s]
    fs_all, un_all, conflicts = [], [], []
    for k in others:
        T_k_s = invert_transform(T_world_scan[k]) @ T
        fs = free_space_violation(pre[k], pre[s], T_k_s, acfg)
        un = unseen_violation(pre[k], pre[s], T_k_s, acfg)
        fs_all.append(fs)
        un_all.append(un)
        seen_through = f"{fs:.3f} of the points in {names[k]}'s free space"
        why = {
            "gross": seen_through,
            "free_space": seen_through,
            "unseen": f"{un:.3f} of the points where {names[k]} saw nothing",
        }
        # A conflict other than a gross one only with a scan that shares surface with
        # this one (why: docs/design/verification.md); the pairwise limits loosened as
        # for a pose not refined on that pair (no ICP of this scan on k tightened it).
        sensors = seen_from_sensors(pre[k], pre[s])
        for kind in view_conflicts(fs, un, k in support, acfg, sensors):
            conflicts.append((k, why[kind], kind == "gross"))
    v.free_space_violation = float(np.nanmax(fs_all)) if np.any(np.isfinite(fs_all)) else None
    v.unseen_violation = float(np.nanmax(un_all)) if np.any(np.isfinite(un_all)) else None
    return conflicts


def settle_conflicts(out, conflicts, scans) -> None:
    """Which side of each conflict loses (``out``: {scan: ScanVerification}, changed in
    place; ``conflicts``: {scan: [(k, why, gross)]}).

    A conflict between s and k counts against s when k's own evidence is stronger: cycle >
    passing the model check > neither, and between two scans that pass the model check,
    the one whose pose more accepted pairs agree with (a pose resting on one pairwise
    estimate loses against one that two or more estimates agree on; equal counts do not
    overrule each other); cycle evidence stands. A gross conflict is compared the same
    way, then on the share of the scan's points the model of the others covers, and
    counts against both sides when they tie; cycle evidence does not stand against it."""
    strength = {
        k: (
            2 if out[k].evidence == "cycle" else 1 if out[k].status == "verified" else 0,
            len(out[k].agreeing_pairs),
        )
        for k in scans
    }

    def covered(k) -> float:
        x = out[k].model_overlap
        return -1.0 if x is None or not np.isfinite(x) else float(x)

    for s in scans:
        v = out[s]
        if v.status == "undetermined":
            continue
        against = []
        for k, why, gross in conflicts.get(s, []):
            if k not in strength:
                continue
            if gross:
                if (*strength[k], covered(k)) >= (*strength[s], covered(s)):
                    against.append(why)
            elif strength[s][0] < 2 and strength[k] > strength[s]:
                against.append(why)
        if against:
            v.reason = "; ".join(([v.reason] if v.reason else []) + against)
            v.status, v.evidence = "unverified", ""
        elif v.status == "verified" and not v.evidence:
            v.evidence = "model"
