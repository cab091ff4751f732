"""What every command shares: turning typed errors into one-line messages and exit codes,
configuration from ``--config`` / ``--set`` / named options, progress bars.

Exit codes (README.md): 0 ok, 2 bad input or usage, 3 some scans not registered,
4 internal or numerical failure, 130 interrupted.
"""

from __future__ import annotations

import json
from pathlib import Path

import typer

STATE = {"debug": False}

SET_HELP = (
    "Any configuration value, SECTION.FIELD=VALUE (repeatable; VALUE as JSON, else text), "
    "e.g. --set refine.rounds=2 --set align.ransac_max_iterations=8000."
)


def fail(exc: BaseException) -> typer.Exit:
    """Print a one-line message for a library error; return the Exit to raise."""
    from mvreg.errors import MvregError

    if STATE["debug"]:
        raise exc
    code = exc.exit_code if isinstance(exc, MvregError) else 4
    msg = str(exc) if isinstance(exc, MvregError) else f"{type(exc).__name__}: {exc}"
    typer.echo(f"mvreg: error: {msg}", err=True)
    return typer.Exit(code)


class Terminated(BaseException):
    """Raised in the main thread by the SIGTERM handler of `run_guarded`."""


# Signals received during the guarded call. An extension module being imported when
# the signal lands turns the handler's exception into an ImportError (pybind11
# "initialization failed"), which a loader may wrap into a file error: the record
# here, not the exception type, decides the exit code.
_received: list[int] = []


def _on_signal(signum, frame):
    import signal

    _received.append(signum)
    raise Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def signal_exit_code() -> int | None:
    """143 (SIGTERM) or 130 (SIGINT) when the last guarded call received a signal, else
    None."""
    import signal

    if not _received:
        return None
    return 143 if _received[0] == signal.SIGTERM else 130


def _signal_exit() -> typer.Exit:
    import signal

    if _received[0] == signal.SIGTERM:
        typer.echo("mvreg: terminated (SIGTERM); this run's outputs were discarded", err=True)
        return typer.Exit(143)
    typer.echo("mvreg: interrupted", err=True)
    return typer.Exit(130)


def run_guarded(fn, *args, **kwargs):
    """Call fn; turn MvregError (and, without --debug, anything else) into an exit code.

    SIGINT exits 130 and SIGTERM 143, each with a message; both unwind the call (so an
    output folder being written is discarded, the previous one kept), whatever
    exception the unwinding ends up as.
    """
    import signal
    import threading

    from mvreg.errors import MvregError

    main = threading.current_thread() is threading.main_thread()
    handled = (signal.SIGTERM, signal.SIGINT)
    previous = {s: signal.signal(s, _on_signal) for s in handled} if main else {}
    _received.clear()
    try:
        return fn(*args, **kwargs)
    except typer.Exit:
        if _received:
            raise _signal_exit() from None
        raise
    except (KeyboardInterrupt, Terminated):
        if not _received:  # raised by the code itself, not by a signal
            _received.append(signal.SIGINT)
        raise _signal_exit() from None
    except MvregError as e:
        raise (_signal_exit() if _received else fail(e)) from None
    except Exception as e:  # noqa: BLE001 - last resort: one line, unless --debug
        raise (_signal_exit() if _received else fail(e)) from None
    finally:
        for s, handler in previous.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)


def parse_sets(items: list[str] | None) -> dict:
    """``["refine.rounds=2", ...]`` -> ``{"refine.rounds": 2}``; values as JSON, else text."""
    from mvreg.errors import ConfigError

    out = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"--set {item!r}: expected SECTION.FIELD=VALUE")
        try:
            value = json.loads(text)
        except ValueError:
            value = text
        out[key.strip()] = value
    return out


def config_from(path: Path | None, sets: list[str] | None, **named):
    """The RegisterConfig: defaults < ``path`` < ``--set`` < named options (None: unset)."""
    from mvreg.config import load_config

    given = {k: v for k, v in named.items() if v is not None}
    return load_config(path, **{**parse_sets(sets), **given})


def check_out_file(path: Path, force: bool, inputs: tuple[Path, ...] = ()):
    """Refuse an --out file that is a folder, one of the ``inputs`` (even with --force),
    or exists without ``force``."""
    from mvreg.errors import InputError, OutputExistsError

    if not str(path) or path.is_dir():
        raise InputError(f"{path or repr('')}: is a folder; --out must name a file")
    for inp in inputs:
        if path.resolve() == Path(inp).resolve():
            raise InputError(f"--out {path}: is the input {inp}; choose another file")
    if path.exists() and not force:
        raise OutputExistsError(f"{path} exists (use --force to overwrite)")


class RichProgress:
    """Progress bars for the pipeline stages (the pipeline calls stage/advance/done)."""

    def __init__(self):
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
        )

        self._p = Progress(
            TextColumn("{task.description:>22}"),
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            transient=False,
        )
        self._task = None
        self._p.start()

    def stage(self, name: str, total: int | None = None) -> None:
        if self._task is not None:
            t = self._p.tasks[self._task]
            self._p.update(self._task, completed=t.total or 1, total=t.total or 1)
        self._task = self._p.add_task(name, total=total if total else 1)

    def advance(self, n: int = 1) -> None:
        if self._task is not None:
            self._p.advance(self._task, n)

    def done(self) -> None:
        self.stage("done", 1)
        self._p.advance(self._task, 1)
        self.stop()

    def stop(self) -> None:
        """Stop the display and its refresh thread (also when the run is interrupted: a
        refresh thread still drawing while the interpreter exits was seen to turn an
        exit code 130 into 1). Idempotent."""
        self._p.stop()
