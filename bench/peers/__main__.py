"""``python -m bench.peers`` = ``python scripts/bench_peers.py``."""

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads

from bench.peers.cli import main  # noqa: E402

main()
