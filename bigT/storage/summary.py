"""The summary of a store that ``bigT info`` prints: :func:`summary`."""

from __future__ import annotations

import numpy as np

from . import _format as fmt


def summary(A) -> dict:
    """Shape, nnz, density, tile fill, diagonal statistics and bytes on disk of the
    :class:`~bigT.storage.BlockCSR` ``A`` (taken as it is, not imported: the reader
    depends on this module, not the other way round)."""
    diag = A.diagonal(output_order="matrix")  # statistics only: no permutation
    n_total = A.grid[0] * A.grid[1]
    n, m = A.shape
    return {
        "path": str(A.path),
        "redirected_from": None if A.redirected_from is None else str(A.redirected_from),
        "format": fmt.FORMAT_NAME,
        "version": A.attrs.version,
        "inner_format": A.inner_format,
        "complete": A.complete,
        "missing_tile_rows": list(A.missing_tile_rows),
        "shape": list(A.shape),
        "dtype": A.dtype.name,
        "nnz": A.nnz,
        "density": A.nnz / (n * m) if n * m else 0.0,
        "nnz_per_row": A.nnz / n if n else 0.0,
        "tile_size": A.tile_size,
        "grid": list(A.grid),
        "n_tiles_stored": A.n_tiles_stored,
        "n_tiles_total": n_total,
        "tile_fill": A.n_tiles_stored / n_total if n_total else 0.0,
        "diagonal_min": float(diag.min()) if diag.size else None,
        "diagonal_max": float(diag.max()) if diag.size else None,
        "zero_diagonal": int(np.count_nonzero(diag == 0)),
        "bytes_on_disk": fmt.disk_bytes(A.path),
        "csr_bytes": A.csr_bytes(),
        "pixel_order": None if A.pixel_order is None else A.pixel_order.to_attrs(),
        "metadata": dict(A.metadata),
    }
