#!/usr/bin/env python3
"""Entry point of :mod:`bench.solvers`: the benchmark, its options and outputs are described there
(``--help``)."""

import importlib.util
import os
import sys
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads
os.environ.setdefault("OMP_NUM_THREADS", "1")  # before numpy loads
if importlib.util.find_spec("bench") is None:  # a checkout where bench is not installed
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.solvers import main  # noqa: E402

if __name__ == "__main__":
    raise SystemExit(main())
