"""Reading and writing matrices in the file formats ``bigT convert``/``export`` know.

Input: scipy ``save_npz`` (.npz), Matrix Market (.mtx, also .mtx.gz), MATLAB (.mat,
read with ``scipy.io.loadmat``; v7.3/HDF5 files are not supported) and dense NumPy
(.npy). Output: .npz and .mtx.
"""

from __future__ import annotations

import io
import os
import zipfile
from pathlib import Path

import numpy as np
import scipy.io
import scipy.sparse as sp

from ..atomic import atomic_output
from ..errors import InvalidMatrixError, StoreError, short_reason
from .objects import ObjectPath, as_location

INPUT_SUFFIXES = (".npz", ".mtx", ".mtx.gz", ".mat", ".npy")
OUTPUT_SUFFIXES = (".npz", ".mtx")


def _suffix(path: Path, known) -> str | None:
    name = path.name.lower()
    return next((s for s in sorted(known, key=len, reverse=True) if name.endswith(s)), None)


def load_matrix(path, var: str | None = None):
    """Load a 2-D matrix (scipy sparse or ndarray) from ``path``.

    Parameters
    ----------
    path : str or os.PathLike
    var : str, optional
        Variable of a .mat file; default the only sparse or 2-D numeric array in it.

    Raises
    ------
    StoreError
        Missing or unreadable file (truncated, corrupt, not of its suffix's format),
        unknown suffix, ambiguous or absent .mat variable.
    InvalidMatrixError
        The file holds something that is not a 2-D matrix of real numbers.
    """
    path = Path(os.fspath(path))
    kind = _suffix(path, INPUT_SUFFIXES)
    if kind is None:
        raise StoreError(f"unknown input format (known: {', '.join(INPUT_SUFFIXES)})", path)
    if not path.is_file():
        raise StoreError("no such file", path)
    try:
        A = _read(path, kind, var)
    except (StoreError, InvalidMatrixError):
        raise
    except Exception as exc:  # parsers of a damaged file raise every type there is
        raise StoreError(f"cannot read as {kind} ({short_reason(exc, path)})", path) from None
    if A.ndim != 2:
        raise InvalidMatrixError(f"holds an array of shape {A.shape}, not a 2-D matrix", path)
    if not (np.issubdtype(A.dtype, np.number) or A.dtype == bool) \
            or np.issubdtype(A.dtype, np.complexfloating):
        raise InvalidMatrixError(f"holds values of dtype {A.dtype}, not real numbers", path)
    return A


def _read(path: Path, kind: str, var: str | None):
    if kind == ".npz":
        return _load_npz(path)
    if kind in (".mtx", ".mtx.gz"):
        return scipy.io.mmread(path)
    if kind == ".npy":
        return np.load(path, allow_pickle=False)
    return _load_mat(path, var)


def _load_npz(path: Path):
    """A scipy ``save_npz`` file; an archive of other arrays (``numpy.savez``) is
    refused with the names it holds."""
    if not zipfile.is_zipfile(path):  # else numpy says "pickled (object) data"
        raise StoreError("cannot read as .npz (not a zip archive: truncated, or another "
                         "format)", path)
    with np.load(path, allow_pickle=False) as archive:
        names = list(archive.files)
    if "format" not in names:
        raise InvalidMatrixError("is a .npz of arrays (" + ", ".join(names[:5])
                                 + "), not a scipy sparse matrix (scipy.sparse.save_npz); "
                                 "save a dense matrix as .npy", path)
    return sp.load_npz(path)


def check_values(A, path, dtype=None) -> None:
    """Refuse values of the loaded matrix ``A`` that its store could not hold.

    Run before the store is written, so the errors name the input file (the store's
    own checks name the store). Integer and boolean values are always representable.

    Parameters
    ----------
    A : scipy sparse matrix or ndarray, as :func:`load_matrix` returns it
    path : the input file, named in the errors
    dtype : {"float32", "float64"}, optional
        The store's dtype; default A's own (float32 for anything but float64).

    Raises
    ------
    InvalidMatrixError
        NaN or Inf values; values beyond the dtype's range (they would become Inf); or
        nonzero values below its smallest normal number (they would be stored subnormal
        or as zero: their reciprocals overflow and ``invert`` fails on them).
    """
    if A.dtype.kind != "f":
        return
    dt = np.dtype(dtype) if dtype is not None else np.dtype(
        np.float64 if A.dtype == np.float64 else np.float32)
    info = np.finfo(dt)
    data = _values(A)
    remedy = (": store float64 ({option}) or scale the matrix (its inverse scales "
              "exactly)" if dt != np.float64 else ": scale the matrix (its inverse scales "
              "exactly)")
    checks = (
        (lambda v: ~np.isfinite(v), "NaN/Inf values", ""),
        (lambda v: np.isfinite(v) & (np.abs(v) > info.max),
         f"values beyond {dt.name}'s range +-{info.max:.3g}", remedy),
        (lambda v: (v != 0) & (np.abs(v) < info.tiny),
         f"nonzero values below {dt.name}'s smallest normal number {info.tiny:.3g}",
         ", which would be stored as 0 or subnormal (their reciprocals overflow)" + remedy),
    )
    for test, what, advice in checks:
        with np.errstate(invalid="ignore"):
            if test(data).any():
                count, row = _count_and_first_row(A, test)
                raise InvalidMatrixError(f"{count} {what} (first in row {row}){advice}", path,
                                         option=("dtype", "float64") if "{option}" in advice else None)


def _values(A) -> np.ndarray:
    if not sp.issparse(A):
        return np.asarray(A)
    return A.data if hasattr(A, "data") else sp.csr_array(A).data


def _count_and_first_row(A, test) -> tuple[int, int]:
    """How many entries of ``A`` pass ``test`` and the row of the first (an error path:
    the copy to COO costs nothing that matters)."""
    if sp.issparse(A):
        coo = sp.coo_array(A)
        hit = np.flatnonzero(test(coo.data))
        return len(hit), int(coo.row[hit].min())
    rows = np.nonzero(test(np.asarray(A)))[0]
    return len(rows), int(rows.min())


def _load_mat(path: Path, var: str | None):
    contents = scipy.io.loadmat(path)
    arrays = {k: v for k, v in contents.items() if not k.startswith("__")}
    candidates = [k for k, v in arrays.items()
                  if sp.issparse(v) or (isinstance(v, np.ndarray) and v.ndim == 2
                                        and np.issubdtype(v.dtype, np.number) and v.size > 1)]
    if var is not None:
        if var not in arrays:
            raise StoreError(f"no variable {var!r} (variables: {', '.join(sorted(arrays)) or 'none'})", path)
        return arrays[var]
    if len(candidates) == 1:
        return arrays[candidates[0]]
    if not candidates:
        raise StoreError(f"no sparse or 2-D numeric variable (variables: "
                         f"{', '.join(sorted(arrays)) or 'none'})", path)
    raise StoreError(f"several matrix variables, choose one with {{option}}: {', '.join(sorted(candidates))}", path,
                     option="var")


def save_matrix(A, path):
    """Write the sparse matrix ``A`` to .npz (scipy save_npz, CSR) or .mtx: a file,
    or an object of object storage (a URL, put whole in one request)."""
    path = as_location(path)
    kind = _suffix(path, OUTPUT_SUFFIXES)
    if kind is None:
        raise StoreError(f"unknown output format (known: {', '.join(OUTPUT_SUFFIXES)})", path)
    if isinstance(path, ObjectPath):
        buffer = io.BytesIO()
        _write_matrix(A, buffer, kind)
        path.write_bytes(buffer.getvalue())
        return path
    # through a file object: given a name, numpy and scipy append a lower-case suffix
    # to one they do not recognise (OUT.NPZ)
    with atomic_output(path, "the exported matrix") as tmp, open(tmp, "wb") as f:
        _write_matrix(A, f, kind)
    return path


def _write_matrix(A, f, kind: str) -> None:
    if kind == ".npz":
        sp.save_npz(f, sp.csr_array(A), compressed=True)
    else:
        scipy.io.mmwrite(f, sp.coo_array(A))
