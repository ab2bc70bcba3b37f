"""How tile-row tasks are wired and run: one dask graph per pass (a term's product, a
mat-vec), built with public calls only (``dask.delayed`` + ``dask.compute``).

* One task per output tile row, named ``f"{op}-{tokenize(...)}"``. Tile pairs with a
  zero factor are filtered out inside the graph builder's row functions from the
  stores' ``tile_indptr``/``tile_indices`` before any tile is read.
* The same code path runs on the local threaded scheduler (default, ``workers``
  threads; the kernels release the GIL) or on a ``distributed.Client``
  (``scheduler=client.get``).
* Tasks carry a small string handle to their context (stores, writers, caches), kept
  in a process-level registry, so the graph holds no large objects and nothing is
  pickled for the threaded scheduler or an in-process ``Client``. A task on a remote
  worker that does not find the handle raises a clear error (see :func:`lookup`).
* Tasks write their tile rows to disk and return only small statistics, so what is in
  memory is bounded by the tasks in flight (``workers``) and the tile cache.
"""

from __future__ import annotations

import itertools
import threading
import time
import uuid

import dask
import numpy as np
from dask.base import tokenize

_REGISTRY: dict[str, object] = {}
_LOCK = threading.Lock()

#: Test hook: when set, called as ``task_hook(op, i)`` at the start of every row task
#: (tests inject a crash mid-term through it).
task_hook = None


class Context:
    """What the tasks of one pass share. Attributes are free-form; ``progress`` (a
    callable taking a count) and ``lock`` are always present."""

    def __init__(self, **items):
        self.lock = threading.Lock()
        self.progress = None
        self.__dict__.update(items)


def register(ctx: Context) -> str:
    handle = uuid.uuid4().hex
    with _LOCK:
        _REGISTRY[handle] = ctx
    return handle


def unregister(handle: str) -> None:
    with _LOCK:
        _REGISTRY.pop(handle, None)


def lookup(handle: str) -> Context:
    try:
        return _REGISTRY[handle]
    except KeyError:
        raise RuntimeError(
            "bigT task context not found: this worker runs in another process. bigT's "
            "product tasks share open stores and writers with the calling process; use a "
            "threaded scheduler or a distributed.Client(processes=False)"
        ) from None


def _run_row(handle: str, fn, op: str, i: int):
    ctx = lookup(handle)
    if task_hook is not None:
        task_hook(op, i)
    t0 = time.perf_counter()
    stats = fn(ctx, i)
    stats = dict(stats or {})
    stats["seconds"] = time.perf_counter() - t0
    if ctx.progress is not None:
        with ctx.lock:
            ctx.progress(1)
    return stats


def scheduler_kwargs(client=None, workers: int = 2) -> dict:
    """Keyword arguments for ``dask.compute``: the client's ``get`` when a
    ``distributed.Client`` is given, else the local threaded scheduler."""
    if client is not None:
        return {"scheduler": client.get}
    return {"scheduler": "threads", "num_workers": max(1, int(workers))}


def build_row_tasks(op: str, fn, rows, ctx: Context, handle: str, token_parts) -> list:
    """One ``dask.delayed`` task per tile row in ``rows``, keyed ``op-token``."""
    call = dask.delayed(_run_row, pure=True)
    return [
        call(handle, fn, op, int(i), dask_key_name=f"{op}-{tokenize(op, token_parts, int(i))}")
        for i in rows
    ]


def run_rows(op: str, fn, rows, ctx: Context, *, token_parts=(), client=None,
             workers: int = 2, wave: int | None = None) -> list[dict]:
    """Run ``fn(ctx, i)`` for every tile row ``i`` in ``rows`` as one dask graph
    (or several of at most ``wave`` tasks each, when given) and return their stats."""
    rows = [int(i) for i in rows]
    if not rows:
        return []
    handle = register(ctx)
    try:
        out = []
        size = len(rows) if not wave else max(1, int(wave))
        it = iter(rows)
        while chunk := list(itertools.islice(it, size)):
            tasks = build_row_tasks(op, fn, chunk, ctx, handle, token_parts)
            out.extend(dask.compute(*tasks, **scheduler_kwargs(client, workers)))
        return out
    finally:
        unregister(handle)


def _matvec_row(ctx, i):
    return {"i": i, "y": ctx.row_matvec(i, ctx.V)}


def matvec(op: str, row_matvec, n_rows_grid: int, row_range, V: np.ndarray, *,
           token_parts=(), client=None, workers: int = 2) -> np.ndarray:
    """Y = A @ V streamed tile row by tile row, one task per tile row.

    Parameters
    ----------
    row_matvec : callable (i, V) -> (rows_i, k) ndarray
    V : (n, k) ndarray
    """
    ctx = Context(row_matvec=row_matvec, V=V)
    res = run_rows(op, _matvec_row, range(n_rows_grid), ctx,
                   token_parts=(token_parts, tokenize(V)), client=client, workers=workers)
    n = row_range(n_rows_grid - 1)[1]
    Y = np.zeros((n, V.shape[1]), dtype=np.result_type(V.dtype, np.float32))
    for r in res:
        a, b = row_range(r["i"])
        Y[a:b] = r["y"]
    return Y
