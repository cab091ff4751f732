#!/usr/bin/env python3
"""mvreg side by side with Open3D multiway, GTSAM and chaining: see :mod:`bench.peers`.

OPENBLAS_NUM_THREADS=1 python scripts/bench_peers.py              # full
OPENBLAS_NUM_THREADS=1 python scripts/bench_peers.py --quick      # bunny + one mesh, M <= 1000
"""

import importlib.util
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads
if importlib.util.find_spec("bench") is None:  # a checkout where bench is not installed
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.peers.cli import main  # noqa: E402

if __name__ == "__main__":
    main()
