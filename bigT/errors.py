"""The bigT error hierarchy.

Every error bigT raises on bad input derives from :class:`BigTError`, itself a
``ValueError`` (as zarr-python's errors are), so callers can catch one class. Each
message names the file (when there is one) and the problem, on one line: the CLI
prints it to stderr and exits with status 2.

An error about an argument carries it in a structured field, :class:`Option`, and its
message names it by the placeholder ``{option}``: ``str(error)`` spells it as Python
does (``overwrite=True``), the command line as its flag (``--overwrite``,
:meth:`BigTError.render`), so a library message holds no command-line flag and the
command line rewrites no library wording.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Callable

#: :attr:`Option.value` of an option named without a value (``memory_limit``).
UNSET: Any = type("Unset", (), {"__repr__": lambda self: "UNSET"})()


@dataclass(frozen=True)
class Option:
    """The argument an error concerns, and the value that would help.

    Attributes
    ----------
    name : str
        The Python argument (``"overwrite"``, ``"first_bounce"``, ``"memory_limit"``).
    value : object
        What to pass (``True``, ``"identity"``); :data:`UNSET` names the argument alone.
    python : str, optional
        How a Python caller does it when ``name=value`` does not say it all
        (``"resume=True, then finalize()"``).
    cli : str, optional
        What a command-line user does where the command line has no flag for it (bigT's
        commands resume by being rerun: ``"rerun the command that wrote it"``).
    """

    name: str
    value: Any = True
    python: str | None = None
    cli: str | None = None

    def as_python(self) -> str:
        """``overwrite=True``, ``first_bounce='identity'``, ``memory_limit``."""
        if self.python is not None:
            return self.python
        return self.name if self.value is UNSET else f"{self.name}={self.value!r}"

    def as_flag(self, flag: str | None = None) -> str:
        """``--overwrite``, ``--first-bounce identity``, ``--memory-limit``.

        Parameters
        ----------
        flag : str, optional
            The command's option string for :attr:`name` (the CLI looks it up by its
            ``dest``); default ``--`` and the name with dashes.
        """
        if flag is None and self.cli is not None:
            return self.cli
        flag = flag or "--" + self.name.replace("_", "-")
        return flag if self.value is UNSET or self.value is True else f"{flag} {self.value}"


def _option(option: Option | str | tuple | None) -> Option | None:
    if option is None or isinstance(option, Option):
        return option
    if isinstance(option, str):
        return Option(option, UNSET)
    return Option(*option)


class BigTError(ValueError):
    """Base of all bigT errors.

    Parameters
    ----------
    message : str
        What is wrong, in words a user can act on; ``{option}`` where the option is named.
    path : str or os.PathLike, optional
        The file or store concerned; prefixed to the message.
    option : Option, str or tuple, optional
        The argument the error concerns: an :class:`Option`, ``(name, value)`` or a
        name alone (``"memory_limit"``).

    Attributes
    ----------
    path : str or None
    option : Option or None
    problem : str
        The message without the path, the option spelt as Python does.
    """

    def __init__(self, message: str, path: str | os.PathLike | None = None, *,
                 option: Option | str | tuple | None = None):
        # a store in object storage is named by its URL (it is no os.PathLike)
        self.path = None if path is None else (
            os.fspath(path) if isinstance(path, (str, os.PathLike)) else str(path))
        self.option = _option(option)
        self.template = message
        self.problem = self._fill(self.option.as_python() if self.option else "")
        super().__init__(self._prefixed(self.problem))

    def _fill(self, spelt: str) -> str:
        return self.template.replace("{option}", spelt) if self.option else self.template

    def _prefixed(self, text: str) -> str:
        return f"{self.path}: {text}" if self.path else text

    def render(self, flag_of: Callable[[str], str | None] = lambda name: None) -> str:
        """The message with the option spelt as a command-line flag.

        Parameters
        ----------
        flag_of : callable, optional
            ``name -> "--flag"`` of the command that ran, None where it has none.
        """
        if self.option is None:
            return str(self)
        # a name the running command has no option for is often another command's
        # (acquire build naming acquire patterns' --superpixel): spelt as a flag too
        return self._prefixed(self._fill(self.option.as_flag(flag_of(self.option.name))))

    def __reduce__(self):
        # dask sends errors between processes: keep the option, not only the text
        return _rebuild, (type(self), self.template, self.path, self.option)


def _rebuild(cls, message, path, option):
    error = cls.__new__(cls)
    BigTError.__init__(error, message, path, option=option)
    return error


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


class CalibrationError(BigTError):
    """Calibration data that cannot be used: a projector ramp that is not monotone or
    is flat, an exposure bracket with a missing exposure, exposures out of order or a
    pixel saturated in every exposure, a response file that is not one."""


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
