"""The mvreg command line: a thin layer over the library.

Each command module maps its options onto the configuration models of :mod:`mvreg.config`
(validated there, once) and calls the library; library code raises typed errors, and only
:func:`mvreg.cli.common.run_guarded` turns them into one-line messages and exit codes
(0 ok, 2 bad input, 3 scans unregistered, 4 failure). Heavy imports happen inside the
commands, so ``mvreg --help`` is instant and ``import mvreg.cli`` loads no algorithm.
"""

from __future__ import annotations

import os
import sys
from typing import Annotated

import typer

from mvreg.cli import register as _register_cmds
from mvreg.cli import solve as _solve_cmds
from mvreg.cli.common import STATE, run_guarded, signal_exit_code
from mvreg.cli.synth import synth_command

__all__ = ["app", "run", "run_guarded"]

app = typer.Typer(
    name="mvreg",
    help="Global multiview registration of 3D scans, with certificates of optimality.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    rich_markup_mode="rich",
)


def _version(value: bool):
    if not value:
        return
    import numpy
    import open3d
    import rerun
    import scipy

    from mvreg import __version__

    typer.echo(
        f"mvreg {__version__} (numpy {numpy.__version__}, scipy {scipy.__version__}, "
        f"open3d {open3d.__version__}, rerun {rerun.__version__})"
    )
    raise typer.Exit(0)


@app.callback()
def main(
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_version, is_eager=True, help="Versions (loads open3d)."
        ),
    ] = False,
    debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks on errors.")] = False,
):
    """mvreg: register many partial 3D scans into one frame, globally (REG-ADMM)."""
    STATE["debug"] = debug
    # rerun's native log (a failed file sink, ...) would add multi-line noise to stderr:
    # mvreg reports those failures itself, one line naming the file. RUST_LOG=warn shows it.
    os.environ.setdefault("RUST_LOG", "off" if not debug else "warn")


for _sub in (_register_cmds.app, _solve_cmds.app):
    for _cmd in _sub.registered_commands:
        app.registered_commands.append(_cmd)
app.command("synth", epilog="Example:  mvreg synth builtin --out scans/ --views 12 --noise 0.002")(
    synth_command
)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())


def run() -> None:
    """The ``mvreg`` program (``python -m mvreg.cli`` too): :data:`app`. After a SIGINT or
    SIGTERM the guarded call received, the run has unwound (outputs discarded) and the
    process ends at once with 130 or 143: a signal that lands while an extension module
    is being imported leaves it half-initialised, and tearing the interpreter down then
    was seen to end the process with 1 instead."""
    try:
        code = _main()
    except (SystemExit, KeyboardInterrupt):
        if signal_exit_code() is None:
            raise
    if signal_exit_code() is None:
        sys.exit(code)
    # Also when the call returned 130 or 143 itself: the interpreter's teardown joins the
    # worker threads, and a KeyboardInterrupt raised then ended the process by SIGINT
    # (-2) instead of 130 once, on a loaded machine.
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(signal_exit_code())


def _main() -> int:
    """:data:`app` with click's usage errors (a bad option value, an unknown option) as
    one line ``mvreg: error: COMMAND: message`` and exit code 2, like every other error."""
    try:
        rv = app(standalone_mode=False)
    except typer.Abort:  # Ctrl-C at a prompt (mvreg has none) or EOF
        return 130
    except typer.TyperException as e:  # click's usage errors (typer vendors click)
        if not hasattr(e, "format_message"):
            raise
        ctx = getattr(e, "ctx", None)
        where = ctx.command_path if ctx is not None else "mvreg"
        message = " ".join(e.format_message().split())
        if message:  # empty: help was shown (no command given)
            typer.echo(f"mvreg: error: {where}: {message}", err=True)
        return int(getattr(e, "exit_code", 2))
    return rv if isinstance(rv, int) else 0
