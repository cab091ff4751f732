#!/usr/bin/env python3
"""Tuned Open3D and KISS-Matcher + mvreg's global stage beside mvreg, on the generalization
runs and the real bunny: see :mod:`bench.peers_generalization`.

OPENBLAS_NUM_THREADS=1 python scripts/bench_peers_generalization.py --work /tmp/pg   # seed 0
"""

import importlib.util
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads
if importlib.util.find_spec("bench") is None:  # a checkout where bench is not installed
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.peers_generalization import main  # noqa: E402

if __name__ == "__main__":
    main()
