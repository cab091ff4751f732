"""Listing a folder of scans and checking one file entry before it is opened.

A scan file must be a regular file (symlinks followed) whose name is valid UTF-8; a
dangling symlink, a symlink loop or an undecodable name raises
:class:`~mvreg.errors.ScanFileError` with the name escaped (``\\xff`` for a byte that is
not UTF-8), so the message can always be printed.
"""

from __future__ import annotations

import errno
import os
import stat
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from mvreg.errors import InputError, ScanFileError


def display_path(path: str | os.PathLike) -> str:
    """``path`` as printable text: bytes that are not UTF-8 escaped as ``\\xNN``."""
    return os.fsencode(path).decode("utf-8", "backslashreplace")


@dataclass
class ScanListing:
    """What :func:`mvreg.io.loaders.scan_folder` found.

    Attributes:
        files: scan files (supported suffixes), natural order.
        skipped: (path, reason) of every other entry that is not hidden and not a known
            sidecar file (unsupported suffix, a sub-folder, ...): warn about them.
    """

    files: list[Path] = field(default_factory=list)
    skipped: list[tuple[Path, str]] = field(default_factory=list)

    def skipped_report(self) -> list[dict]:
        """``[{"file": name, "reason": reason}, ...]`` for report.json."""
        return [{"file": display_path(p.name), "reason": r} for p, r in self.skipped]


def check_file_entry(path: Path) -> int:
    """Size in bytes of a readable regular file; ScanFileError otherwise."""
    shown = display_path(path)
    try:
        os.fsencode(path).decode("utf-8")
    except UnicodeDecodeError:
        raise ScanFileError(shown, "the file name is not valid UTF-8") from None
    try:
        st = os.stat(path)
    except FileNotFoundError:
        if os.path.islink(path):
            target = display_path(os.readlink(path))
            raise ScanFileError(shown, f"dangling symbolic link (to {target})") from None
        raise ScanFileError(shown, "no such file") from None
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise ScanFileError(shown, "symbolic link loop") from None
        raise ScanFileError(shown, f"cannot read file ({e.strerror or e})") from None
    if stat.S_ISDIR(st.st_mode):
        raise ScanFileError(shown, "is a folder, not a scan file")
    if not stat.S_ISREG(st.st_mode):
        raise ScanFileError(shown, "not a regular file")
    return int(st.st_size)


def list_folder(folder: Path, suffixes: set[str], ignored: Callable[[str], bool]) -> ScanListing:
    """Entries of ``folder``: scan files (checked), and skipped ones with the reason."""
    if not folder.is_dir():
        raise InputError(f"{display_path(folder)}: not a folder")
    listing = ScanListing()
    for p in folder.iterdir():
        if ignored(p.name):
            continue
        if p.suffix.lower() not in suffixes:
            kind = "a folder" if p.is_dir() else f"unsupported file type {p.suffix!r}"
            if p.is_symlink() and not p.exists():
                kind = "dangling symbolic link"
            listing.skipped.append((p, kind))
        elif p.is_dir():
            listing.skipped.append((p, "a folder"))
        else:
            check_file_entry(p)
            listing.files.append(p)
    return listing
