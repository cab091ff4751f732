"""Settings and formatting shared by the peer benchmark's modules.

CONDITIONS: data_synth.synthesize_scans arguments per synthetic condition; ROT_OK_DEG /
TR_OK_PCT: targets used only to count "within target" runs; TIE / TIE_TIME: relative
differences reported as ties; PATCH: make_problem arguments of the patch problems;
METHOD_ORDER: the order of the methods in tables and plots.
"""

from __future__ import annotations

import numpy as np

CONDITIONS = {  # data_synth.synthesize_scans arguments per condition
    "clean": dict(noise=0.0, outliers=0.0),
    "noise 0.5%": dict(noise=0.005, outliers=0.0),
    "outliers 10%": dict(noise=0.0, outliers=0.1),
}
# Targets of the register issue, used only to count "within target" runs.
ROT_OK_DEG, TR_OK_PCT = 0.5, 0.5
TIE = 0.05  # relative error differences below 5% are reported as ties
TIE_TIME = 0.10  # and time differences below 10% (the machine is shared)

PATCH = dict(d=3, degree=6, nodes_per_pair=20, noise=0.01)

REFERENCE = "truth (reference)"
METHOD_ORDER = [
    "mvreg",
    "mvreg/spectral",
    "mvreg/gpm",
    "mvreg/balm",
    "mvreg/c-admm",
    "mvreg/no-refine",
    "open3d",
    "open3d/all-uncertain",
    "open3d/mvreg-pairs",
    "gtsam",
    "chain/mvreg-pairs",
    "chain/open3d-pairs",
    REFERENCE,
]


def fmt(x, fmt=".3f"):
    return "n/a" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, fmt)


def ratio(a, b):
    if a is None or b is None or not np.isfinite(a) or not np.isfinite(b) or b <= 0:
        return "n/a"
    return f"{a / b:.2g}"


def ordered_methods(rows):
    seen = list(dict.fromkeys(r["method"] for r in rows))
    return sorted(seen, key=lambda m: METHOD_ORDER.index(m) if m in METHOD_ORDER else 99)
