"""``python -m mvreg.cli``: the mvreg command line."""

from mvreg.cli import run

run()
