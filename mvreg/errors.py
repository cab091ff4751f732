"""Typed errors raised by the library. Only the CLI turns them into messages and exit codes.

Exit codes (documented in README.md):
    0  success (all scans registered)
    2  bad input or usage (InputError and subclasses)
    3  some scans could not be registered (reported, the rest written)
    4  internal / numerical failure (SolverError)
"""

from __future__ import annotations


class MvregError(Exception):
    """Base class of every error mvreg raises on purpose."""

    exit_code = 4


class InputError(MvregError):
    """Bad input: a file, a value or a parameter the user gave. Exit code 2."""

    exit_code = 2


class ScanFileError(InputError):
    """A scan file is unreadable, empty, all-NaN or has too few points."""

    def __init__(self, path, reason: str):
        self.path = str(path)
        self.reason = reason
        super().__init__(f"{self.path}: {reason}")

    def __reduce__(self):  # pickled back from a worker process (Dask)
        return (type(self), (self.path, self.reason))


class ProblemError(InputError):
    """A patch problem is malformed (NaN, bad indices, duplicate observations, ...)."""


class DisconnectedError(ProblemError):
    """The patch graph has several connected components.

    Attributes:
        components: list of lists of patch names, largest first.
    """

    def __init__(self, components: list[list[str]]):
        self.components = components
        parts = "; ".join(
            "{" + ", ".join(c[:8]) + (", ..." if len(c) > 8 else "") + "}" for c in components
        )
        super().__init__(
            f"the patch graph is disconnected into {len(components)} components: {parts}"
        )

    def __reduce__(self):
        return (type(self), (self.components,))


class IllPosedError(ProblemError):
    """Some rotation is not determined by the data (lambda_{d+1}(C) ~ 0).

    Attributes:
        patches: names of the patches that share fewer than d+1 nodes with the rest
            (may be empty when the degeneracy is not local to a patch).
    """

    def __init__(self, message: str, patches: list[str]):
        self.patches = patches
        super().__init__(message)

    def __reduce__(self):
        return (type(self), (str(self), self.patches))


class ConfigError(InputError):
    """An absurd or inconsistent parameter value."""


class OutputExistsError(InputError):
    """The output already holds results and --force was not given."""


class SolverError(MvregError):
    """A numerical failure inside a solver."""


class TaskError(MvregError):
    """A per-scan or per-pair task failed (in-process or on a Dask worker).

    Attributes:
        task: what the task worked on, e.g. ``"pair scan_001.ply, scan_004.ply"``.
        reason: the original error, as ``"Type: message"``.
    """

    def __init__(self, task: str, reason: str):
        self.task = task
        self.reason = reason
        super().__init__(f"{task}: {reason}")

    def __reduce__(self):  # pickled back from a worker process
        return (type(self), (self.task, self.reason))
