"""Atomic file writes: write to a temporary file beside the target, then rename.

A failed write (disk full, read-only, ...) raises :class:`OutputWriteError` naming the
target file; the target is left untouched and the temporary file removed.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path

from mvreg.errors import MvregError


class OutputWriteError(MvregError):
    """An output file could not be written (disk full, permissions, ...). Exit code 4.

    Attributes:
        path: the file that was being written (as text).
        reason: the operating system's reason.
    """

    def __init__(self, path, reason: str):
        self.path, self.reason = str(path), reason
        super().__init__(f"{self.path}: cannot write ({reason})")

    def __reduce__(self):  # pickled back from a worker process (Dask)
        return (type(self), (self.path, self.reason))

    def relocate(self, staging: Path, final: Path) -> None:
        """Name the file at ``final`` instead of inside the ``staging`` folder."""
        try:
            rel = Path(self.path).relative_to(staging)
        except ValueError:
            return
        self.path = str(final / rel)
        self.args = (f"{self.path}: cannot write ({self.reason})",)


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None):
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    Use for writers that insist on a file name (open3d, rerun). On an exception the
    temporary file is removed and ``path`` is left untouched.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(
            prefix=f".{path.name}.", suffix=suffix or path.suffix or ".tmp", dir=path.parent
        )
    except OSError as e:
        raise OutputWriteError(path, e.strerror or str(e)) from e
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; results should be normal files
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except OSError as e:
        Path(tmp).unlink(missing_ok=True)
        raise OutputWriteError(path, e.strerror or str(e)) from e
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj, default: Callable | None = None) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, default=default or _json_default) + "\n")


def _json_default(o):
    import numpy as np

    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serializable: {type(o).__name__}")
