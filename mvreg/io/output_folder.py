"""A run's output folder, replaced as one consistent set.

    with OutputFolder("result", force=True, inputs=["scans"]) as staging:
        write_poses_json(staging / "poses.json", ...)   # everything goes into staging
    # on success: "result" now holds exactly the new set; on an exception: unchanged

Contract:

- The outputs are written into a fresh staging folder beside OUT (same file system),
  ``.OUT.mvreg-tmp-<pid>``, then swapped in: when OUT exists, with one atomic
  ``renameat2(RENAME_EXCHANGE)`` on Linux (else OUT is first renamed aside to
  ``.OUT.mvreg-old-<pid>``), then the old set is deleted. A crash or SIGKILL at any
  moment leaves either the old complete set or the new one in OUT, never a mix, and stale
  files of an older run never survive ``force``.
- Staging and set-aside folders of dead processes are removed by the next run (a set-aside
  old set is moved back when OUT is missing).
- Refused before anything is written (:class:`~mvreg.errors.InputError`): an empty OUT,
  OUT equal to, inside or containing an input folder, or the current folder; OUT holding
  files mvreg did not write (even with ``force``: a user's folder is never deleted); OUT
  holding results without ``force`` (:class:`~mvreg.errors.OutputExistsError`).
- Files are committed with mode ``0666 & ~umask`` (0644 under the usual umask), whatever
  the writer used (rerun writes 0600); hidden temporary files are not committed.
- A write error (disk full, ...) raised by :mod:`mvreg.io.atomic` names the file at its
  final place in OUT; the old set stays intact.
"""

from __future__ import annotations

import ctypes
import errno
import os
import re
import shutil
import stat
from collections.abc import Iterable
from pathlib import Path

from mvreg.errors import InputError, OutputExistsError
from mvreg.io.atomic import OutputWriteError

#: Files ``mvreg register`` writes into its output folder.
RESULT_FILES = (
    "poses.json",
    "poses_tum.txt",
    "poses_kitti.txt",
    "merged.ply",
    "merged.laz",  # output.merged_format
    "merged.e57",
    "report.json",
    "recording.rrd",
)
_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def exchange_paths(a: Path, b: Path) -> bool:
    """Atomically exchange two paths (Linux ``renameat2``). False when not supported."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (AttributeError, OSError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    fn.restype = ctypes.c_int
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP):
        return False
    raise OSError(err, os.strerror(err), str(b))


def _remove(path: Path) -> None:
    if path.is_symlink() or not path.is_dir():
        path.unlink(missing_ok=True)
    else:
        shutil.rmtree(path, ignore_errors=True)


class OutputFolder:
    """Context manager yielding a staging folder that replaces ``out`` on success.

    Args:
        out: the output folder (created when missing).
        force: replace a folder that already holds results.
        inputs: folders read by the run: OUT may not equal, lie inside, or contain one.
        owned: names of the files mvreg writes (anything else in OUT is a user's file).
    """

    def __init__(
        self,
        out: str | os.PathLike,
        *,
        force: bool = False,
        inputs: Iterable[str | os.PathLike] = (),
        owned: Iterable[str] = RESULT_FILES,
    ):
        if not str(out).strip() or str(out).strip() in (".", ".."):
            raise InputError(f"--out {str(out)!r}: give a named output folder")
        self.out = Path(out).resolve() if Path(out).is_symlink() else Path(out).absolute()
        self.shown = Path(out)
        self.force = force
        self.inputs = [Path(p) for p in inputs]
        self.owned = frozenset(owned)
        self.staging = self.out.parent / f".{self.out.name}.mvreg-tmp-{os.getpid()}"

    # ---------------------------------------------------------------- checks
    def _is_owned(self, name: str) -> bool:
        return name in self.owned or any(name.startswith(f".{o}.") for o in self.owned)

    def check(self) -> None:
        """Refuse a bad OUT before any work is done (also done on entering)."""
        out = self.out.resolve()
        cwd = Path.cwd().resolve()
        if out == cwd or out in cwd.parents:
            raise InputError(f"{self.shown}: is the current folder (or holds it); choose another")
        for inp in self.inputs:
            i = inp.resolve()
            if out == i or i in out.parents:
                raise InputError(f"{self.shown}: is inside the input folder {inp}; choose another")
            if out in i.parents:
                raise InputError(f"{self.shown}: holds the input folder {inp}; choose another")
        if self.out.exists() and not self.out.is_dir():
            raise OutputExistsError(f"{self.shown}: exists and is not a folder")
        if not self.out.is_dir():
            return
        names = sorted(os.listdir(self.out))
        foreign = [n for n in names if not self._is_owned(n)]
        if foreign:
            raise OutputExistsError(
                f"{self.shown}: holds files mvreg did not write ({', '.join(foreign[:5])}"
                + (", ..." if len(foreign) > 5 else "")
                + "); choose another --out (it is never deleted, even with --force)"
            )
        results = [n for n in names if n in self.owned]
        if results and not self.force:
            raise OutputExistsError(
                f"{self.shown}: already holds results ({', '.join(results)}); "
                "use --force to overwrite"
            )

    def remove_stale(self) -> None:
        """Delete staging / set-aside folders of dead runs (restore a lost OUT)."""
        pattern = re.compile(rf"\.{re.escape(self.out.name)}\.mvreg-(tmp|old)-(\d+)")
        if not self.out.parent.is_dir():
            return
        for entry in self.out.parent.iterdir():
            m = pattern.fullmatch(entry.name)
            if not m or int(m.group(2)) == os.getpid() or _pid_alive(int(m.group(2))):
                continue
            if m.group(1) == "old" and not self.out.exists():
                os.rename(entry, self.out)  # the swap was cut between its two renames
            else:
                _remove(entry)

    # ---------------------------------------------------------------- protocol
    def __enter__(self) -> Path:
        self.check()
        try:
            self.out.parent.mkdir(parents=True, exist_ok=True)
            self.remove_stale()
            _remove(self.staging)
            self.staging.mkdir()
        except OSError as e:  # read-only or missing place: name OUT, not the staging
            raise OutputWriteError(self.shown, e.strerror or str(e)) from e
        return self.staging

    def __exit__(self, exc_type, exc, tb) -> bool:
        if exc_type is None:
            try:
                self.commit()
            except BaseException:
                _remove(self.staging)
                raise
            return False
        _remove(self.staging)
        if isinstance(exc, OutputWriteError):
            exc.relocate(self.staging, self.shown)
        return False

    def staged(self, path: str | os.PathLike) -> Path:
        """Where to write a file meant for OUT (inside the staging folder); others unchanged."""
        path = Path(path)
        try:
            return self.staging / path.absolute().relative_to(self.out)
        except ValueError:
            return path

    def final_path(self, path: str | os.PathLike) -> Path:
        """Where a file written into the staging folder ends up (others unchanged)."""
        path = Path(path)
        try:
            return self.shown / path.relative_to(self.staging)
        except ValueError:
            return path

    def commit(self) -> None:
        """Fix modes, drop temporary files, swap the staging folder in, delete the old set."""
        umask = os.umask(0)
        os.umask(umask)
        for entry in self.staging.iterdir():
            if entry.name.startswith("."):
                _remove(entry)
            elif entry.is_file() and not entry.is_symlink():
                os.chmod(entry, stat.S_IMODE(0o666 & ~umask))
        _fsync_dir(self.staging)
        try:
            self._swap()
        except OSError as e:  # e.g. OUT is a mount point: it cannot be renamed
            raise OutputWriteError(
                self.shown, f"cannot replace the folder: {e.strerror or e}"
            ) from e
        _fsync_dir(self.out.parent)

    def _swap(self) -> None:
        if not self.out.exists():
            os.rename(self.staging, self.out)
        elif exchange_paths(self.staging, self.out):
            _remove(self.staging)  # now the old set
        else:
            old = self.out.parent / f".{self.out.name}.mvreg-old-{os.getpid()}"
            os.rename(self.out, old)
            os.rename(self.staging, self.out)
            _remove(old)


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
