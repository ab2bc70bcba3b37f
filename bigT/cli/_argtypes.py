"""Argument types of the ``bigT`` command line: ``type=`` callables for argparse.

Each one turns the text of an option into its value or raises
:class:`argparse.ArgumentTypeError` with a message saying what is wrong and what is
expected; argparse then prints the usage and ``bigT CMD: error: argument --opt:
<message>`` and exits with status 2, before any file is read or written. (A
``ValueError`` from a type would be reported only as "invalid <name> value".)

The factories (:func:`integer`, :func:`number`) follow argparse-addons'
``Integer(lo, hi)``: a range checked at parse time, so every option's domain is written
once, beside the option.
"""

from __future__ import annotations

import argparse
import math
import re
from typing import Any, Callable

from ..sizes import parse_size

__all__ = ["integer", "number", "memory_size", "size_or_zero", "image_size", "scheduler_address",
           "clip_range", "density", "json_object"]


def _fail(message: str) -> argparse.ArgumentTypeError:
    return argparse.ArgumentTypeError(message)


def _range_words(lo, hi, lo_open: bool = False, hi_open: bool = False) -> str:
    if hi is None:
        return f"{'>' if lo_open else '>='} {lo:g}"
    return f"in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"


def _checked(convert, in_range, what: str, name: str, shown) -> Callable[[str], Any]:
    """The parser of :func:`integer` and :func:`number`: ``convert`` the stripped text,
    then require ``in_range``; ``shown(value, text)`` is how a value out of range is
    quoted in the message."""

    def parse(text: str):
        try:
            value = convert(text.strip())
        except ValueError:
            raise _fail(f"must be {what}, got {text!r}") from None
        if not in_range(value):
            raise _fail(f"must be {what}, got {shown(value, text)}")
        return value

    parse.__name__ = name
    return parse


def integer(lo: int, hi: int | None = None) -> Callable[[str], int]:
    """An argparse type: a whole number in ``[lo, hi]`` (``hi`` None: no upper bound).

    Parameters
    ----------
    lo, hi : int
        The smallest and largest values accepted.

    Returns
    -------
    callable
        ``str -> int``, raising ``ArgumentTypeError`` for anything else.
    """
    what = f"an integer {_range_words(lo, hi)}"
    in_range = (lambda value: lo <= value and (hi is None or value <= hi))
    return _checked(int, in_range, what, f"integer {_range_words(lo, hi)}",
                    lambda value, text: value)


def number(lo: float, hi: float | None = None, *, lo_open: bool = False,
           hi_open: bool = False) -> Callable[[str], float]:
    """An argparse type: a finite real number between ``lo`` and ``hi``.

    NaN and infinities are always refused: no bigT option has a use for them, and NaN
    slips through every ``<`` test a later check would make.

    Parameters
    ----------
    lo, hi : float
        Bounds; ``hi`` None for none.
    lo_open, hi_open : bool
        Exclude the bound itself (``number(0, lo_open=True)``: strictly positive).
    """
    what = f"a finite number {_range_words(lo, hi, lo_open, hi_open)}"

    def in_range(value: float) -> bool:
        below = value <= lo if lo_open else value < lo
        above = hi is not None and (value >= hi if hi_open else value > hi)
        return math.isfinite(value) and not below and not above

    return _checked(float, in_range, what, what, lambda v, text: repr(text.strip()))


def memory_size(text: str) -> int:
    """An argparse type: a size in bytes as :func:`bigT.sizes.parse_size` reads it
    (``4GiB``, ``500MB``, ``2G``, ``1e9``; dask's syntax)."""
    try:
        return parse_size(text)
    except ValueError:
        raise _fail(f"must be a positive memory size such as 4GiB or 500MB, got {text!r}") from None


memory_size.__name__ = "memory size"


def size_or_zero(text: str) -> int:
    """An argparse type: :func:`memory_size`, or 0 (``0``, ``0MiB``: none at all)."""
    try:
        if float(text.strip().rstrip("kKmMgGtTpPiIbB") or "nan") == 0:
            return 0
    except ValueError:
        pass
    try:
        return parse_size(text)
    except ValueError:
        raise _fail(f"must be a memory size such as 1GiB or 500MB, or 0, got {text!r}") from None


size_or_zero.__name__ = "size"


def image_size(text: str) -> tuple[int, int]:
    """An argparse type: an image size ``HxW`` (also ``H,W``), both >= 1."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX,]\s*(\d+)\s*", text)
    if not m:
        raise _fail(f"must look like HxW (e.g. 96x128), got {text!r}")
    h, w = int(m.group(1)), int(m.group(2))
    if h < 1 or w < 1:
        raise _fail(f"needs a height and width of at least 1 pixel, got {text!r}")
    return h, w


image_size.__name__ = "image size HxW"


def json_object(text: str) -> str:
    """``text`` when it is a JSON object (``--storage-options``), refused here else."""
    import json

    try:
        value = json.loads(text)
    except ValueError as exc:
        raise _fail(f"must be a JSON object, got {text!r:.60} ({exc})") from None
    if not isinstance(value, dict):
        raise _fail(f'must be a JSON object such as {{"region": "eu-west-1"}}, got {text!r:.60}')
    return text


def scheduler_address(text: str) -> str:
    """An argparse type: ``local:N`` (N >= 1 worker processes) or the address of a dask
    scheduler, ``[PROTOCOL://]HOST:PORT`` with a port in 1..65535 (``inproc://`` needs
    none). Whether it answers is checked when the command connects."""
    s = text.strip()
    local = re.fullmatch(r"local:(\S*)", s)
    if local:
        if not local.group(1).isdigit() or int(local.group(1)) < 1:
            raise _fail(f"local:N needs N >= 1 worker processes, got {text!r}")
        return s
    if s == "threads" or s.startswith("inproc://"):
        return s
    m = re.fullmatch(r"(?:[a-z][a-z0-9+.-]*://)?(\[[0-9a-f:.]+\]|[^\s:/\[\]]+):(\d+)", s,
                     flags=re.IGNORECASE)
    if not m or not 1 <= int(m.group(2)) <= 65535:
        raise _fail(f"must be local:N or a scheduler address tcp://HOST:PORT, got {text!r}")
    return s


scheduler_address.__name__ = "scheduler address"


def clip_range(text: str) -> tuple[float | None, float | None] | None:
    """An argparse type: ``LO,HI`` with either side empty for no bound (``0,`` clips
    below only), or ``none`` for no clipping. Bounds are finite and LO < HI."""
    if text.strip().lower() in ("none", "off", ""):
        return None
    parts = [s.strip() for s in text.split(",")]
    usage = f"must be LO,HI (e.g. 0,1 or 0,) or 'none', got {text!r}"
    if len(parts) != 2:
        raise _fail(usage)
    try:
        lo, hi = (float(p) if p else None for p in parts)
    except ValueError:
        raise _fail(usage) from None
    if any(v is not None and not math.isfinite(v) for v in (lo, hi)):
        raise _fail(f"needs finite bounds (leave a side empty for none), got {text!r}")
    if lo is not None and hi is not None and lo >= hi:
        raise _fail(f"needs LO < HI, got {text!r}")
    return lo, hi


clip_range.__name__ = "clip range"


def density(presets) -> Callable[[str], str | float]:
    """An argparse type: one of ``presets`` or a form-factor cut (a finite number >= 0)."""
    cut = number(0)

    def parse(text: str):
        if text.strip() in presets:
            return text.strip()
        try:
            return cut(text)
        except argparse.ArgumentTypeError:
            raise _fail(f"must be one of {', '.join(presets)} or a form-factor cut (a "
                        f"finite number >= 0), got {text!r}") from None

    parse.__name__ = "density"
    return parse
