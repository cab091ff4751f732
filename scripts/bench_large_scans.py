#!/usr/bin/env python3
"""Entry point of :mod:`bench.large_scans`: the benchmark, its options and outputs are described there
(``--help``)."""

import importlib.util
import sys
from pathlib import Path

if importlib.util.find_spec("bench") is None:  # a checkout where bench is not installed
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.large_scans import main  # noqa: E402

if __name__ == "__main__":
    main()
