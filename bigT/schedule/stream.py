"""Streaming products of a block-CSR store with dense frame batches.

One pass reads every tile row of the matrix once and multiplies it against all K
columns of the batch, so K frames cost one read of the matrix (compensation streams
row tiles of X against image batches). Tile rows are independent (they write disjoint
row ranges of the result), so they are tasks of the schedule layer's runner: a few
local threads by default (reading and decompressing one tile row overlaps the product
of another; both release the GIL), or the workers of a dask cluster. Decoded tiles are
kept between passes in the process's tile cache (:mod:`bigT.schedule.cache`), the one
the engine uses too. Used by compensation and by the target-error probes of the
algorithms layer.
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np

from .. import config
from ..errors import ShapeMismatchError
from ..storage.channel_mixing import mixed_product

# The runner and the passes (matvec, worker) are imported inside the functions: they
# import dask (~0.3 s), which compensating with X held in memory never needs.


def compute_dtype(store) -> np.dtype:
    """Dtype of the dense batches streamed against ``store`` (float32 at least)."""
    return np.result_type(np.dtype(store.dtype), np.float32)


def stream_matmul(A, V: np.ndarray, *, runner=None, workers: int | None = None,
                  progress: bool = False, desc: str = "pass",
                  cache_bytes: int | None = None) -> np.ndarray:
    """A @ V with A streamed from disk one tile row at a time, V and the result in the
    store's stored (matrix) order: the streaming primitive under compensation, which
    converts images with :mod:`bigT.storage.frames` (``BlockCSR @ x`` is the row-major
    form a user calls).

    Parameters
    ----------
    A : BlockCSR, shape (n_rows, n_cols)
    V : ndarray, shape (n_cols, K) or (n_cols,), in A's stored order
    runner : bigT.schedule.runner runner, optional
        Where the tile rows run (a dask cluster's workers, say); default: local threads.
    workers : int, optional
        Threads of the default runner (default ``config.COMPENSATE_WORKERS``).
    progress : bool
        Show a progress bar over tile rows.
    cache_bytes : int, optional
        Decoded tiles kept for the next pass in each process's tile cache (default 0:
        every tile is read from disk; :func:`~bigT.compensation.compensate` keeps
        ``config.COMPENSATE_CACHE_BYTES`` for the batches of one call).

    Returns
    -------
    ndarray, shape (n_rows, K) or (n_rows,), dtype ``compute_dtype(A)``
    """
    from .matvec import matvec, matvec_spec  # these two import dask (see above)
    from .runner import ThreadRunner, worker_path

    n_rows, n_cols = A.shape
    dtype = compute_dtype(A)
    V = np.asarray(V)
    squeeze = V.ndim == 1
    if V.ndim not in (1, 2) or V.shape[0] != n_cols:
        raise ShapeMismatchError(f"cannot multiply a {n_rows}x{n_cols} matrix by an array of "
                                 f"shape {V.shape}")
    V = np.ascontiguousarray(V.reshape(n_cols, -1), dtype=dtype)
    if runner is None:
        runner = ThreadRunner(max(1, min(int(workers or config.COMPENSATE_WORKERS), A.grid[0])))
    budget = 0 if cache_bytes is None else int(cache_bytes)
    spec = matvec_spec(desc, worker_path(A.path), n_rows, A.tile_size, A.dtype,
                       cache_bytes=budget)

    def stored_product(W: np.ndarray) -> np.ndarray:  # S W of the tiles the workers read
        W = np.ascontiguousarray(W, dtype=dtype)
        return matvec(runner, spec, W, progress=progress).astype(dtype, copy=False)

    # a factored colour store (an inverse by the global-mixing path) is L S R
    out = mixed_product(getattr(A, "mixing", None), stored_product, V)
    return out[:, 0] if squeeze else out


@contextmanager
def scheduler_runner(scheduler):
    """The runner of ``scheduler`` (:func:`bigT.schedule.runner.open_runner`) for the
    duration of the block, closed after; None (local threads) when none is given; a
    runner itself is passed through (and left open)."""
    from .runner import ClusterRunner, ThreadRunner, open_runner  # dask (see above)

    if scheduler is None or isinstance(scheduler, (ThreadRunner, ClusterRunner)):
        yield scheduler
        return

    runner = open_runner(scheduler)
    try:
        yield runner
    finally:
        runner.close()


def cache_budget(cache_bytes: int | None) -> int:
    """The tile-cache budget of a compensation call (default
    ``config.COMPENSATE_CACHE_BYTES``)."""
    return config.COMPENSATE_CACHE_BYTES if cache_bytes is None else max(0, int(cache_bytes))


def forget_tiles(runner, *stores) -> None:
    """Drop the cached tiles of ``stores`` in every process that ran the passes (the
    end of a compensation call: a library's caller should not keep a gigabyte of
    tiles)."""
    from .worker import end_pass  # the worker module's state: only once passes ran

    from .runner import worker_path

    paths = tuple(worker_path(s.path) for s in stores if s is not None)
    if runner is None:
        end_pass(None, paths)
    else:
        runner.end_pass(None, paths)
