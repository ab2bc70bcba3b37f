"""Sizes in bytes, written as dask writes them: ``4GiB``, ``500MB``, ``2G``, ``1e9``.

One parser for every size bigT reads (``--memory-limit``, ``--cache-size``,
``memory_limit=``): the syntax and the unit table of :func:`dask.utils.parse_bytes`
(SI prefixes are powers of 1000, binary prefixes ``Ki``, ``Mi``, ... powers of 1024, a
trailing ``B`` optional, case ignored), written out here so that a command that never
schedules anything does not import dask (~0.3 s) to read an option. The tests check it
against dask's own parser.
"""

from __future__ import annotations

import math
import re

#: Multipliers of the units, as ``dask.utils.byte_sizes`` has them.
_UNITS = {"": 1, "k": 10**3, "m": 10**6, "g": 10**9, "t": 10**12, "p": 10**15,
          "ki": 2**10, "mi": 2**20, "gi": 2**30, "ti": 2**40, "pi": 2**50}
_SIZE = re.compile(r"(\d+(?:\.\d*)?(?:e[+-]?\d+)?|\.\d+(?:e[+-]?\d+)?)\s*([kmgtp]i?)?b?",
                   re.IGNORECASE)


def parse_size(value: int | float | str, name: str = "size") -> int:
    """Bytes of a size such as ``4GiB``, ``500MB``, ``2G``, ``1e9`` or an integer.

    Parameters
    ----------
    value : int, float or str
        The size; a number is bytes.
    name : str
        What the size is, for the error message (``"memory_limit"``).

    Returns
    -------
    int
        Bytes, at least 1.

    Raises
    ------
    ValueError
        Unreadable, negative, zero or not finite, naming ``name`` and the value.
    """
    if isinstance(value, bool):
        number = math.nan
    elif isinstance(value, (int, float)):
        number = float(value)
    else:
        m = _SIZE.fullmatch(str(value).strip())
        number = float(m.group(1)) * _UNITS[(m.group(2) or "").lower()] if m else math.nan
    if not math.isfinite(number) or number < 1:  # also: no match, '-5GiB', 'inf', '1e999'
        raise ValueError(f"{name} must be a positive size such as 4GiB or 500MB, "
                         f"got {value!r}")
    return int(number)


def format_size(n_bytes: float) -> str:
    """``4294967296`` -> ``'4GiB'``: the shortest binary-prefixed form that
    :func:`parse_size` reads back to within 0.05 % (defaults shown in ``--help``)."""
    n = float(n_bytes)
    for unit, mult in (("PiB", 2**50), ("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20),
                       ("KiB", 2**10)):
        if n >= mult:
            return f"{n / mult:.4g}{unit}"
    return f"{int(n)}B"
