"""Streaming products of a block-CSR store with dense frame batches.

One pass reads every tile row of the matrix once and multiplies it against all K
columns of the batch, so K frames cost one read of the matrix (DESIGN.md: compensation
streams row tiles of X against image batches). Tile rows are independent (they write
disjoint row ranges of the result), so they are spread over a few threads: reading and
decompressing one tile row overlaps the product of another, and both release the GIL.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor, as_completed

import numpy as np

from .. import config
from ..errors import ShapeMismatchError, StoreError


def as_store(A, name: str = "matrix"):
    """A BlockCSR for ``A``: a BlockCSR (returned as is) or the path of a store."""
    if isinstance(A, (str, os.PathLike)):
        from ..storage import open as open_store

        return open_store(A)
    if hasattr(A, "get_tile_row") and hasattr(A, "tile_row_range"):
        return A
    raise StoreError(f"{name} must be a bigT store (BlockCSR) or the path of one, "
                     f"got {type(A).__name__}")


def compute_dtype(store) -> np.dtype:
    """Dtype of the dense batches streamed against ``store`` (float32 at least)."""
    return np.result_type(np.dtype(store.dtype), np.float32)


def _spmm():
    """``spmm(A, X, out)``: out += A @ X, single-threaded (the threads are ours)."""
    try:
        from ..kernels import spmm_dense
    except ImportError:
        spmm_dense = None
    if spmm_dense is None:
        def spmm(A, X, out):
            out += A @ X
    else:
        def spmm(A, X, out):
            spmm_dense(A, X, out=out, n_threads=1)
    return spmm


class TileCache:
    """Decoded tiles kept between passes, up to a byte budget; the rest is re-read.

    A stream of frame batches makes one pass over X per batch; when X (or the part of it
    that fits) stays decoded, later passes skip the read and the decompression. Memory
    stays bounded by ``max_bytes`` whatever the matrix size.

    Parameters
    ----------
    max_bytes : int, optional
        Budget for the CSR arrays of cached tiles (default
        ``config.COMPENSATE_CACHE_BYTES``; 0 disables the cache).
    """

    def __init__(self, max_bytes: int | None = None):
        self.max_bytes = int(config.COMPENSATE_CACHE_BYTES if max_bytes is None else max_bytes)
        self.bytes = 0
        self.hits = self.misses = 0
        self._tiles = {}
        self._lock = threading.Lock()

    def get(self, A, i: int, j: int):
        key = (id(A), i, j)
        tile = self._tiles.get(key)
        if tile is not None:
            self.hits += 1
            return tile
        self.misses += 1
        tile = A.get_tile(i, j)
        if self.max_bytes > 0:
            size = tile.data.nbytes + tile.indices.nbytes + tile.indptr.nbytes
            with self._lock:
                if self.bytes + size <= self.max_bytes and key not in self._tiles:
                    self._tiles[key] = tile
                    self.bytes += size
        return tile


def stream_matmul(A, V: np.ndarray, *, workers: int | None = None, progress: bool = False,
                  desc: str = "pass", cache: TileCache | None = None) -> np.ndarray:
    """A @ V with A streamed from disk one tile row at a time.

    Parameters
    ----------
    A : BlockCSR, shape (n_rows, n_cols)
    V : ndarray, shape (n_cols, K) or (n_cols,)
    workers : int, optional
        Threads over tile rows (default ``config.COMPENSATE_WORKERS``).
    progress : bool
        Show a tqdm bar over tile rows.
    cache : TileCache, optional
        Keep decoded tiles for the next pass (none: every tile is read from disk).

    Returns
    -------
    ndarray, shape (n_rows, K) or (n_rows,), dtype ``compute_dtype(A)``
    """
    n_rows, n_cols = A.shape
    dtype = compute_dtype(A)
    V = np.asarray(V)
    squeeze = V.ndim == 1
    if V.ndim not in (1, 2) or V.shape[0] != n_cols:
        raise ShapeMismatchError(f"cannot multiply a {n_rows}x{n_cols} matrix by an array of "
                                 f"shape {V.shape}")
    V = np.ascontiguousarray(V.reshape(n_cols, -1), dtype=dtype)
    out = np.zeros((n_rows, V.shape[1]), dtype=dtype)
    spmm = _spmm()

    ts = A.tile_size

    def one_row(i):
        # Tile by tile: no copy assembling the tile row, and each product touches only
        # the rows of V under its tile.
        start, stop = A.tile_row_range(i)
        for j in A.tile_columns(i):
            j = int(j)
            tile = A.get_tile(i, j) if cache is None else cache.get(A, i, j)
            if tile.nnz:
                spmm(tile, V[j * ts:j * ts + tile.shape[1]], out[start:stop])
        return i

    n_tile_rows = A.grid[0]
    workers = max(1, min(int(workers or config.COMPENSATE_WORKERS), n_tile_rows))
    from tqdm.auto import tqdm

    # delay: passes shorter than a second draw no bar at all
    with tqdm(total=n_tile_rows, desc=desc, unit="tile row", leave=False, delay=1.0,
              disable=not progress) as bar:
        if workers == 1:
            for i in range(n_tile_rows):
                one_row(i)
                bar.update()
        else:
            with ThreadPoolExecutor(workers) as pool:
                for fut in as_completed([pool.submit(one_row, i) for i in range(n_tile_rows)]):
                    fut.result()
                    bar.update()
    return out[:, 0] if squeeze else out
