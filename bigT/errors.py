"""The bigT error hierarchy.

Every error bigT raises on bad input derives from :class:`BigTError`, itself a
``ValueError`` (as zarr-python's errors are), so callers can catch one class. Each
message names the file (when there is one) and the problem, on one line: the CLI
prints it to stderr as it is and exits with status 2.
"""

from __future__ import annotations

import os


class BigTError(ValueError):
    """Base of all bigT errors.

    Parameters
    ----------
    message : str
        What is wrong, in words a user can act on.
    path : str or os.PathLike, optional
        The file or store concerned; prefixed to the message.
    """

    def __init__(self, message: str, path: str | os.PathLike | None = None):
        self.path = None if path is None else os.fspath(path)
        self.problem = message
        super().__init__(f"{self.path}: {message}" if self.path else message)


class InvalidMatrixError(BigTError):
    """A matrix holds values bigT cannot use: NaN/Inf, indices out of range,
    unsorted or malformed CSR arrays, a zero or negative diagonal."""


class ShapeMismatchError(BigTError):
    """Shapes, tile sizes or image sizes that do not agree."""


class NotSquareError(ShapeMismatchError):
    """A square matrix was needed."""


class StoreError(BigTError):
    """A path that is not a (readable) bigT store."""


class IncompleteStoreError(StoreError):
    """A store whose writing was interrupted: some tile rows are not marked complete."""


class CorruptStoreError(StoreError):
    """A store with a missing chunk, a checksum mismatch or inconsistent metadata."""


class MemoryLimitError(BigTError):
    """An operation would need more memory than the configured limit allows."""


class DivergenceError(BigTError):
    """The Neumann series diverges: the spectral radius of M = I - T F^-1 is >= 1."""


class ImageError(BigTError):
    """An image that cannot be used: wrong size, wrong channel count, NaN."""


class AcquisitionError(BigTError):
    """Patterns or captures that cannot make a transport matrix: a missing or extra
    capture, one of the wrong size or bit depth, a manifest of another projector,
    captures that are all black."""


class DiskFullError(BigTError):
    """The disk filled while writing; what was complete before is kept."""


class OutputError(BigTError):
    """An output file that cannot be written (read-only file system, no permission, a
    folder where a file is asked); whatever was at its path before is left as it was."""


class TaskError(BigTError):
    """A task of a pass failed for a reason outside bigT's own checks (a bug, a lost
    file, a dead worker); the message names the pass, the rows and the cause."""


class SchedulerError(BigTError):
    """A scheduler that cannot be used: unreachable, or workers that cannot reach the
    stores."""


class MemoryLimitWarning(UserWarning):
    """A memory limit may be exceeded: something the plan cannot bound has grown."""


def short_reason(exc: BaseException, path: str | os.PathLike | None = None) -> str:
    """A foreign exception as a clause of a one-line bigT message: its type and the
    first sentence of its text, the path (which the bigT error names itself) replaced
    by "the file", at most 120 characters.

    Parameters
    ----------
    exc : the exception a reader (numpy, scipy, imageio, zarr) raised
    path : the file it was reading, optional
    """
    text = str(exc)
    if path is not None:
        text = text.replace(os.fspath(path), "the file")
    text = " ".join(text.split(". ")[0].split()).rstrip(".")
    text = f"{type(exc).__name__}: {text}" if text else type(exc).__name__
    return text if len(text) <= 120 else text[:117] + "..."
