"""Reading and writing matrices in the file formats ``bigT convert``/``export`` know.

Input: scipy ``save_npz`` (.npz), Matrix Market (.mtx, also .mtx.gz), MATLAB (.mat,
read with ``scipy.io.loadmat``; v7.3/HDF5 files are not supported) and dense NumPy
(.npy). Output: .npz and .mtx.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import scipy.io
import scipy.sparse as sp

from ..errors import InvalidMatrixError, StoreError

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
        Missing or unreadable file, unknown suffix, ambiguous or absent .mat variable.
    InvalidMatrixError
        The file holds something that is not a 2-D numeric matrix.
    """
    path = Path(os.fspath(path))
    kind = _suffix(path, INPUT_SUFFIXES)
    if kind is None:
        raise StoreError(f"unknown input format (known: {', '.join(INPUT_SUFFIXES)})", path)
    if not path.is_file():
        raise StoreError("no such file", path)
    try:
        if kind == ".npz":
            A = sp.load_npz(path)
        elif kind in (".mtx", ".mtx.gz"):
            A = scipy.io.mmread(path)
        elif kind == ".npy":
            A = np.load(path, allow_pickle=False)
        else:
            A = _load_mat(path, var)
    except (StoreError, InvalidMatrixError):
        raise
    except (OSError, ValueError, KeyError, NotImplementedError, EOFError) as exc:
        raise StoreError(f"cannot read as {kind} ({type(exc).__name__}: {exc})", path) from None
    if A.ndim != 2:
        raise InvalidMatrixError(f"holds an array of shape {A.shape}, not a 2-D matrix", path)
    if not sp.issparse(A) and not (np.issubdtype(A.dtype, np.number) or A.dtype == bool):
        raise InvalidMatrixError(f"holds values of dtype {A.dtype}, not numbers", path)
    return A


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
    raise StoreError(f"several matrix variables, choose one with --var: {', '.join(sorted(candidates))}", path)


def save_matrix(A, path) -> Path:
    """Write the sparse matrix ``A`` to .npz (scipy save_npz, CSR) or .mtx."""
    path = Path(os.fspath(path))
    kind = _suffix(path, OUTPUT_SUFFIXES)
    if kind is None:
        raise StoreError(f"unknown output format (known: {', '.join(OUTPUT_SUFFIXES)})", path)
    if kind == ".npz":
        sp.save_npz(path, sp.csr_array(A), compressed=True)
    else:
        scipy.io.mmwrite(path, sp.coo_array(A))
    return path
