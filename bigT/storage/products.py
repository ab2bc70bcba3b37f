"""What a store computes from its tiles, in its own (matrix) order: the product with a
dense block (:func:`matmul_tiles`) and the main diagonal (:func:`diagonal_of_tiles`);
and the pixel orders its public vectors are given in or asked for
(:data:`VECTOR_ORDERS`, :func:`reordering`, :func:`to_row_major`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse as sp

from .attrs import StoreAttrs
from .pixel_order import PixelOrder
from .tiles import TileRowReader

#: Orders a pixel-indexed vector or matrix is given in or asked for: "row-major", the
#: order of ``image.ravel()`` (the public default), or "matrix", the store's own pixel
#: order (the engine's, free of any permutation). A store that records no pixel order
#: maps no image: both then name its one order.
VECTOR_ORDERS = ("row-major", "matrix")

def reordering(stored: PixelOrder | None, order: str, name: str) -> PixelOrder | None:
    """The store's PixelOrder ``stored`` when vectors in ``order`` must be permuted to
    or from the stored order, else None (matrix order asked, no pixel order recorded,
    or a row-major store: no permutation to pay).

    Raises
    ------
    ValueError
        ``order`` is not one of VECTOR_ORDERS (the message names ``name``).
    """
    if order not in VECTOR_ORDERS:
        raise ValueError(f"{name} must be one of {VECTOR_ORDERS}, got {order!r}")
    if order == "matrix" or stored is None or stored.order == "row-major":
        return None
    return stored


def to_row_major(matrix: sp.csr_array, order: PixelOrder) -> sp.csr_array:
    """(n, n) ``matrix`` in the stored order with rows and columns permuted to
    row-major image order, sorted."""
    inv = order.inverse_permutation
    out = sp.csr_array(matrix[inv][:, inv])
    out.sort_indices()
    return out


def matmul_tiles(attrs: StoreAttrs, iter_tiles: TileRowReader, X: np.ndarray) -> np.ndarray:
    """(n_rows, k) product of the stored matrix with C-contiguous X (n_cols, k),
    streaming tile rows through ``bigT.kernels.spmm_dense`` where there is one."""
    Y = np.zeros((attrs.shape[0], X.shape[1]), dtype=X.dtype)
    spmm = _spmm_dense()
    for i in range(attrs.grid[0]):
        r0, r1 = attrs.tile_row_range(i)
        for j, tile in iter_tiles(i):
            c0 = j * attrs.tile_size
            xs = X[c0:c0 + tile.shape[1]]
            if spmm is None:
                Y[r0:r1] += tile @ xs
            else:
                spmm(tile, xs, out=Y[r0:r1])
    return Y


def matmul_rows(attrs: StoreAttrs, tile_row, X: np.ndarray) -> np.ndarray:
    """(n_rows, k) product of the stored matrix with C-contiguous X (n_cols, k), a
    tile row ``tile_row(i)`` (global columns) at a time."""
    Y = np.zeros((attrs.shape[0], X.shape[1]), dtype=X.dtype)
    spmm = _spmm_dense()
    for i in range(attrs.grid[0]):
        r0, r1 = attrs.tile_row_range(i)
        row = tile_row(i)
        if not row.nnz:
            continue
        if spmm is None:
            Y[r0:r1] += row @ X
        else:
            spmm(row, X, out=Y[r0:r1])
    return Y


def diagonal_of_tiles(attrs: StoreAttrs,
                      diagonal_tile: Callable[[int], sp.csr_array | None]) -> np.ndarray:
    """(min(shape),) main diagonal in the stored order, from the diagonal tiles
    ``diagonal_tile(i)`` (tile (i, i), or None when it is not stored)."""
    n = min(attrs.shape)
    out = np.zeros(n, dtype=attrs.dtype)
    for i in range(min(attrs.grid)):
        tile = diagonal_tile(i)
        if tile is None:
            continue
        d = tile.diagonal()
        r0 = i * attrs.tile_size
        out[r0:r0 + d.size] = d[:n - r0]
    return out


def _spmm_dense():
    """``bigT.kernels.spmm_dense`` when the kernels layer provides it, else None."""
    try:
        from ..kernels import spmm_dense  # numba: only once a product is taken
    except ImportError:
        return None
    return spmm_dense
