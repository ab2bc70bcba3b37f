"""Mat-vec passes: Y = M V or Y = A V for dense V of shape (n, k), one task per row
block, V shared by the pass (scattered once to a cluster's workers). The tasks return
their rows of Y (dense, k columns): the only task results that hold more than counts.
"""

from __future__ import annotations

import numpy as np

from ._backend import spmm_dense
from .spec import BlockStats, MemoryPolicy, PassSpec, row_blocks
from .runner import new_pass_id
from .worker import STATE, TaskContext, _identity


def m_matvec_task(ctx: TaskContext) -> BlockStats:
    """Rows of M V (:meth:`~.operators.MOperand.matvec_rows`)."""
    V = ctx.shared["V"]
    y = ctx.M.matvec_rows(ctx.start, ctx.stop, V, ctx.minus_finv_v(V))
    return ctx.stats(y=y)


def m_abs_matvec_task(ctx: TaskContext) -> BlockStats:
    """Rows of |M| V (:meth:`~.operators.MOperand.abs_matvec_rows`)."""
    return ctx.stats(y=ctx.M.abs_matvec_rows(ctx.start, ctx.stop, ctx.shared["V"]))


def m_largest_task(ctx: TaskContext) -> BlockStats:
    """The largest entry of each of the block's rows of M, shape (rows, 1)
    (:meth:`~.operators.MOperand.largest_entries`; the pass's V is not used)."""
    return ctx.stats(y=ctx.M.largest_entries(ctx.start, ctx.stop))


def store_matvec_task(ctx: TaskContext) -> BlockStats:
    """Rows of A V for the pass's input ``A``: its tile row, read whole (format 2),
    or tile by tile (format 1: no tile row is assembled), through the tile cache."""
    V = ctx.shared["V"]
    path = ctx.spec.input_path("A")
    A = STATE.store(path)
    i, ts = ctx.block.index, A.tile_size
    out = np.zeros((ctx.stop - ctx.start, V.shape[1]), np.result_type(V.dtype, A.dtype))
    ident = _identity(path)
    if A.row_layout:  # the row is stored whole: one read, one product
        if ctx.spec.cache_tiles:
            row = ctx.cache.get((path, ident, "row", i), lambda: A.get_tile_row(i))
        else:
            row = A.get_tile_row(i)
        if row.nnz:
            spmm_dense(row, V, out=out, n_threads=1)
        return ctx.stats(y=out)
    for j in A.tile_columns(i):
        j = int(j)
        if ctx.spec.cache_tiles:
            tile = ctx.cache.get((path, ident, "tile", i, j), lambda j=j: A.get_tile(i, j))
        else:
            tile = A.get_tile(i, j)
        if tile.nnz:
            spmm_dense(tile, V[j * ts:j * ts + tile.shape[1]], out=out, n_threads=1)
    return ctx.stats(y=out)


def matvec_spec(op: str, store_path: str, n: int, block_rows: int, dtype, *,
                memory: MemoryPolicy | None = None, cache_bytes: int | None = None,
                T: str | None = None, first_bounce: str = "",
                zero_diagonal: bool = False, cache_tiles: bool = True,
                largest: bool = False, absolute: bool = False) -> PassSpec:
    """The spec of A V for the store at ``store_path`` (``T`` given: of M V, of |M| V
    when ``absolute``, or of the largest entry of each row of M when ``largest``).
    ``cache_bytes`` 0 caches nothing and leaves the tile cache as it is."""
    if cache_bytes == 0:
        cache_bytes, cache_tiles = None, False
    if T:
        task = m_largest_task if largest else m_abs_matvec_task if absolute else m_matvec_task
    else:
        task = store_matvec_task
    return PassSpec(
        op=op, term=0, task=task,
        T=T or store_path, first_bounce=first_bounce, zero_diagonal=zero_diagonal, n=n,
        block_rows=block_rows, dtype=np.dtype(dtype).name,
        memory=memory or MemoryPolicy(None, 1, n, 0), inputs=(("A", store_path),),
        cache_bytes=cache_bytes, cache_tiles=cache_tiles)


def matvec(runner, spec: PassSpec, V: np.ndarray, shared: dict | None = None, *,
           progress: bool = False) -> np.ndarray:
    """Y = A V (or M V) of shape (n, k) through ``runner``, one task per row block."""
    spec = spec.replace(pass_id=new_pass_id())
    blocks = row_blocks(spec.n, spec.block_rows)
    try:
        stats = runner.map(spec, blocks, {**(shared or {}), "V": V}, progress=progress)
    finally:
        runner.end_pass(spec.pass_id)
    Y = np.zeros((spec.n, V.shape[1]), dtype=np.result_type(V.dtype, np.dtype(spec.dtype),
                                                            np.float32))
    for b, s in zip(blocks, stats):
        Y[b.start:b.stop] = s.y
    return Y
