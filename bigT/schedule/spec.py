"""What a task receives and returns: small, frozen, picklable records.

A pass (one term's product, one mat-vec) is a :class:`PassSpec` and a list of
:class:`RowBlock` keys; each task gets the spec, one key and the pass's shared vectors
(F^-1, F, the active mask, a mat-vec operand V), which travel once per pass (scattered
to the workers of a cluster). A task opens the stores named by path itself, writes its
own rows and returns a :class:`BlockStats`: never a matrix.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable

import numpy as np


@dataclass(frozen=True)
class RowBlock:
    """Rows ``start:stop`` of a pass's output: tile row ``index`` of the output stores
    (or of the operand, for a mat-vec)."""

    index: int
    start: int
    stop: int


def row_blocks(n: int, block_rows: int, indices=None) -> list[RowBlock]:
    """The row blocks of ``n`` rows cut every ``block_rows``; only ``indices`` when
    given."""
    count = -(-n // block_rows)
    chosen = range(count) if indices is None else indices
    return [RowBlock(int(i), int(i) * block_rows, min((int(i) + 1) * block_rows, n))
            for i in chosen]


@dataclass(frozen=True)
class MemoryPolicy:
    """What a process needs to plan its memory (:func:`bigT.schedule.memory.plan_memory`).

    ``limit`` caps the process (None: no cap beyond a worker's own limit); ``threads``
    is the tasks in flight in a process of the local scheduler (a cluster worker uses
    its own thread count); ``max_row_nnz`` the entries of M's widest tile row as made
    from T's (T's, times 3 for a colour F, whose 3x3 blocks spread each entry of T over
    its pixel's 3 columns: at most).
    """

    limit: int | None
    threads: int
    n_cols: int
    max_row_nnz: int


@dataclass(frozen=True)
class PassSpec:
    """One pass of the engine, as every task of it sees it.

    Attributes
    ----------
    op : str
        Name of the pass (task keys, progress bars, errors).
    term : int
    task : callable ``task(ctx: TaskContext) -> BlockStats``
        A module-level function (pickled by reference).
    T : str
        Absolute path of the transport store.
    first_bounce : str
        Digest of F: M's rows are cached under it.
    zero_diagonal : bool
        F = diag T (M's diagonal is exactly 0).
    n : int
    block_rows : int
        Rows of one block; the output stores' tile size.
    dtype : str
    memory : MemoryPolicy
    inputs : tuple of (name, absolute store path)
    scaled : tuple of str
        Inputs read as diag(F) B (S = F X).
    outputs : tuple of (name, absolute store path)
        Stores created before the pass; each task writes its own tile row.
    right : str or None
        The input multiplied from the right (held whole or read in batches).
    threshold : float
        Prune threshold of the pass's products.
    feed_threshold : float or None
        The power form's threshold on P_k, the factor of the next product, when it
        is pruned harder than the term added to X (None: ``threshold``).
    operator_threshold : float or None
        The power form's threshold on M's entries inside the products of the terms
        k >= 2 (M P_{k-1}); term 1 adds M pruned at ``threshold`` only (None: M whole).
    kernel_threads : int
        Threads of one product (1 when tasks already fill the threads).
    pass_id : str
        Unique per pass: a worker lets go of the previous pass's shared factor.
    cache_bytes : int or None
        The tile cache's budget during the pass (compensation); None: the memory plan's.
    cache_tiles : bool
        A mat-vec keeps the tiles it reads in the cache (compensation's batches reuse
        them; the engine's X of one term is read once, and would only evict M's rows).
    """

    op: str
    term: int
    task: Callable
    T: str
    first_bounce: str
    zero_diagonal: bool
    n: int
    block_rows: int
    dtype: str
    memory: MemoryPolicy
    inputs: tuple[tuple[str, str], ...] = ()
    scaled: tuple[str, ...] = ()
    outputs: tuple[tuple[str, str], ...] = ()
    right: str | None = None
    threshold: float = 0.0
    feed_threshold: float | None = None
    operator_threshold: float | None = None
    kernel_threads: int = 1
    pass_id: str = ""
    cache_bytes: int | None = None
    cache_tiles: bool = True

    def input_path(self, name: str) -> str:
        return dict(self.inputs)[name]

    def output_path(self, name: str) -> str:
        return dict(self.outputs)[name]

    def replace(self, **changes) -> "PassSpec":
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class BlockStats:
    """What one task reports.

    Attributes
    ----------
    index : int, the row block
    seconds : float, time in the task
    worker : str, ``pid@host`` of the process that ran it
    nnz_P, nnz_X : int, entries of the new term's rows (P, or M S, or R) and of X's
    computed, skipped : int, tile products done, and pairs skipped (a zero factor)
    row_skipped : bool, the rows were carried over (every factor met a converged row)
    y : (stop - start, k) ndarray or None, a mat-vec's rows
    multiply_adds : int, the multiply-adds of the task's sparse products
    kernel_seconds : float, the time spent inside the product kernel
    bytes_read, bytes_written, read_calls, write_calls : int, the task's thread's I/O
        (:class:`~.costs.ThreadIO`)
    bytes_read_shared : int, the part of ``bytes_read`` read once for every task of
        the pass in this process (a right factor held whole)
    resident_bytes : int, the process's resident set when the task ended
    """

    index: int
    seconds: float = 0.0
    worker: str = ""
    nnz_P: int = 0
    nnz_X: int = 0
    computed: int = 0
    skipped: int = 0
    row_skipped: bool = False
    y: np.ndarray | None = None
    multiply_adds: int = 0
    kernel_seconds: float = 0.0
    bytes_read: int = 0
    bytes_written: int = 0
    read_calls: int = 0
    write_calls: int = 0
    bytes_read_shared: int = 0
    resident_bytes: int = 0

    def replace(self, **changes) -> "BlockStats":
        return dataclasses.replace(self, **changes)
