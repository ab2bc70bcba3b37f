"""Reading the calibration package's JSON files as hostile input: the size bounded
before a byte is parsed, the document's kind and version checked, every array field
checked for type, shape and finiteness, each fault one line naming the file."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..errors import CalibrationError, short_reason

#: Largest calibration JSON file read (a 65536-entry RGB camera table as JSON is about
#: 4 MiB; a projector response of a few thousand levels, a few hundred KiB).
MAX_JSON_BYTES = 8 << 20


def read_document(path: str | os.PathLike, kind: str, version: int) -> dict:
    """The JSON object of a calibration file of ``kind`` (its ``"format"`` field).

    Parameters
    ----------
    path : the file
    kind : str, the expected ``"format"`` value (``"bigT.projector_response"``)
    version : int, the highest ``"version"`` this bigT reads

    Raises
    ------
    CalibrationError
        A missing file, one over :data:`MAX_JSON_BYTES`, not JSON, not an object, of
        another kind or a newer version; naming the file.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise CalibrationError("no such file", path) from None
    except OSError as exc:
        raise CalibrationError(f"cannot read it ({short_reason(exc, path)})", path) from None
    if size > MAX_JSON_BYTES:
        raise CalibrationError(f"{size:,} bytes, more than the {MAX_JSON_BYTES:,} a {kind} "
                               "file may have; refused before parsing it", path)
    try:
        doc = json.loads(path.read_bytes())
    except (OSError, ValueError, RecursionError) as exc:
        raise CalibrationError(f"not a readable JSON file ({short_reason(exc, path)})",
                               path) from None
    if not isinstance(doc, dict):
        raise CalibrationError(f"not a {kind} file: the JSON is a {type(doc).__name__}, "
                               "not an object", path)
    if doc.get("format") != kind:
        raise CalibrationError(f"not a {kind} file (its \"format\" is "
                               f"{str(doc.get('format'))[:40]!r})", path)
    if not isinstance(doc.get("version"), int) or not 1 <= doc["version"] <= version:
        raise CalibrationError(f"{kind} version {json.dumps(doc.get('version'))[:20]} is "
                               f"not one this bigT reads (1 to {version})", path)
    return doc


def number_array(doc: dict, key: str, ndim: int, path) -> np.ndarray:
    """``doc[key]``, a nested list of finite numbers of ``ndim`` dimensions, as float64.

    Raises
    ------
    CalibrationError
        The key missing, ragged lists, strings, booleans, NaN or Inf; naming the file
        and the key.
    """
    if key not in doc:
        raise CalibrationError(f"the field {key!r} is missing", path)
    value = doc[key]
    if not _is_nested_numbers(value, ndim):
        raise CalibrationError(f"the field {key!r} is not a {ndim}-dimensional list of "
                               "numbers", path)
    try:
        array = np.asarray(value, dtype=np.float64)
    except (ValueError, OverflowError):
        raise CalibrationError(f"the field {key!r} is a ragged list", path) from None
    if array.ndim != ndim:
        raise CalibrationError(f"the field {key!r} is a ragged list", path)
    if not np.isfinite(array).all():
        raise CalibrationError(f"the field {key!r} holds a NaN or an infinity", path)
    return array


def _is_nested_numbers(value, ndim: int) -> bool:
    # bool is an int in Python: true/false in a table of numbers is a fault, not 1/0
    if ndim == 0:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    return isinstance(value, list) and all(_is_nested_numbers(v, ndim - 1) for v in value)


def string_list(doc: dict, key: str, path, choices: tuple[tuple[str, ...], ...]) -> tuple[str, ...]:
    """``doc[key]``, a list of strings equal to one of ``choices``.

    Raises
    ------
    CalibrationError
        Naming the file, the key and the accepted values.
    """
    value = doc.get(key)
    if not isinstance(value, list) or tuple(value) not in choices:
        accepted = " or ".join(json.dumps(list(c)) for c in choices)
        raise CalibrationError(f"the field {key!r} must be {accepted}", path)
    return tuple(value)
