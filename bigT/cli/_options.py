"""Option blocks shared by the sub-commands: each written once, so that an option means
one thing, says its default and reads the same wherever it appears.

Conventions
-----------
* Sizes are written as dask writes them (``512MiB``, ``4GiB``, ``2e9``; read by
  :func:`bigT.sizes.parse_size`) and defaults are shown the same way
  (:func:`bigT.sizes.format_size`).
* ``--json`` is a flag: the command prints its report as one JSON object on standard
  output *instead of* the text, so it composes with a pipe or a redirection
  (``bigT info X.zarr --json | jq .nnz``, ``> report.json``) as ``gh --json`` and
  ``pip list --format json`` do. (``invert --json FILE``, its older form, still writes
  FILE.)
* A default the library has is the library's own value, never restated: the constant
  its signature takes, read from a module that imports nothing heavy
  (:mod:`bigT.config`, :mod:`bigT.algorithms.defaults`), so that printing a help
  imports no engine.
* A renamed option keeps its old spelling as a hidden alias that still works and says,
  on standard error, what replaced it.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any, Callable

from ..sizes import format_size
from ._argtypes import integer, memory_size, scheduler_address, size_or_zero


def add_progress(p: argparse.ArgumentParser) -> None:
    """``--no-progress`` -> ``args.progress`` False (``--quiet`` implies it)."""
    p.add_argument("--no-progress", dest="progress", action="store_false",
                   help="no progress bars")


def add_json(p: argparse.ArgumentParser, what: str = "the summary") -> None:
    """``--json``: ``what`` as one JSON object on stdout, in place of the text."""
    p.add_argument("--json", action="store_true",
                   help=f"print {what} as one JSON object on stdout instead of the text")


def add_scheduler(p: argparse.ArgumentParser, what: str = "passes",
                  note: str = "") -> None:
    """``--scheduler ADDRESS|local:N``: where the tile rows run (worker *processes*;
    ``--threads`` counts the threads of the default local run)."""
    p.add_argument("--scheduler", type=scheduler_address, default=None,
                   metavar="ADDRESS|local:N",
                   help=f"run the {what} on a dask cluster: a scheduler address "
                        f"(tcp://HOST:PORT{note}), or local:N for N worker processes "
                        "started for this command (default: threads of this process)")


def add_threads(p: argparse.ArgumentParser, default: int) -> None:
    """``--threads N`` (dest ``workers``, the library's name); ``--workers`` its
    deprecated alias."""
    p.add_argument("--threads", dest="workers", type=integer(1), default=default,
                   metavar="N",
                   help="threads of this process that run the tasks when no --scheduler "
                        f"is given (default {default})")
    p.add_argument("--workers", dest="workers", type=integer(1), action=deprecated("--threads"),
                   help=argparse.SUPPRESS)


def add_size(p: argparse.ArgumentParser, flag: str, *, dest: str, default: int | None,
             help: str, zero: str | None = None) -> None:
    """A size option ``flag SIZE`` (dask's syntax), its default shown as a size.

    Parameters
    ----------
    help : str
        What the size bounds; "(default ...)" is appended.
    zero : str, optional
        What 0 means, where 0 is allowed (``"re-read every pass"``).
    """
    shown = "none" if default is None else format_size(default)
    tail = f"; 0: {zero}" if zero else ""
    p.add_argument(flag, dest=dest, type=size_or_zero if zero else memory_size,
                   default=None, metavar="SIZE", help=f"{help} (default {shown}{tail})")


def deprecated(replacement: str, convert: Callable[[Any], Any] = lambda v: v,
               show: Callable[[Any], str] = str):
    """An argparse action for an old spelling: stores ``convert(value)`` where
    ``replacement`` stores its value, and says on stderr what to write instead
    (``show(value)``: the value as ``replacement`` is written)."""

    class Deprecated(argparse.Action):
        def __call__(self, parser, namespace, values, option_string=None):
            value = convert(values)
            print(f"{parser.prog}: warning: {option_string} is deprecated, write "
                  f"{replacement} {show(value)}", file=sys.stderr)
            setattr(namespace, self.dest, value)

    return Deprecated


def add_memory_limit(p: argparse.ArgumentParser, *, default: int | None, bounds: str,
                     dest: str = "memory_limit") -> None:
    """``--memory-limit SIZE``: a budget of memory the command holds; ``bounds`` says of
    what, the default is shown as a size (or "no limit")."""
    shown = "no limit" if default is None else format_size(default)
    p.add_argument("--memory-limit", dest=dest, type=memory_size, default=None,
                   metavar="SIZE", help=f"{bounds} (default {shown})")
