"""What runs inside any process that executes bigT tasks: the caller's own threads,
or a ``dask worker`` process of a cluster.

Each process keeps its own state (:class:`_ProcessState`): the stores it has opened
(keyed by path and the identity of their root ``zarr.json``, so a store rewritten in
place is opened afresh), one :class:`~.cache.TileCache`, its memory plans, and the
right factor of the pass in progress. A task is ``run_block(spec, block, shared)``:
it builds a :class:`TaskContext` from those, runs ``spec.task`` and returns a
:class:`~.spec.BlockStats`. Errors other than bigT's own reach the caller as a
one-line :class:`~bigT.errors.TaskError`.
"""

from __future__ import annotations

import os
import socket
import sys
import threading
import time

import numpy as np
import scipy.sparse as sp

from ..errors import BigTError, DiskFullError, TaskError
from . import blocks
from ._backend import (BlockDiagonal, KeptTiles, as_location, is_url, open_store,
                       read_store_attrs, release_workspaces, row_marker, store_identity,
                       write_tile_row)
from .cache import TileCache
from .costs import shared_read_bytes, thread_io
from .memory import (PARTIAL_BYTES_PER_ENTRY, MemoryPlan, plan_memory, resident_bytes,
                     return_freed_memory_above)
from .operators import MOperand, StoreOperand, needed_rows, t_row_key
from .spec import BlockStats, MemoryPolicy, PassSpec, RowBlock

#: Test hook: when set, called as ``task_hook(op, index)`` at the start of every task
#: (tests inject a crash mid-term through it; threads of the calling process only).
task_hook = None


def _identity(path) -> tuple:
    """What changes when a store's root zarr.json is rewritten (its inode and mtime,
    an object's ETag)."""
    return store_identity(path)


class _PassState:
    """What the tasks of one pass share in a process: its operands (so a right factor is
    read whole once), its vectors cast to the pass's dtype, M, a mat-vec's -F^-1 V."""

    def __init__(self):
        # reentrant: making one item may get another (M needs F^-1 in the pass's dtype)
        self.lock = threading.RLock()
        self.items: dict = {}

    def get(self, key, make):
        """The item under ``key``, made by ``make()`` by the first task that asks (the
        others wait for it rather than make their own)."""
        with self.lock:
            if key not in self.items:
                self.items[key] = make()
            return self.items[key]

    def release(self) -> None:
        with self.lock:
            items = list(self.items.values())
            self.items.clear()
        for item in items:
            if isinstance(item, StoreOperand):
                item.release()


#: Passes whose shared items a process keeps at once (two runs may share a cluster);
#: the oldest is let go when a task of another pass arrives.
_MAX_PASSES = 4


class _ProcessState:
    """Open stores, the tile cache, memory plans and the passes in progress of this
    process (module-level singleton :data:`STATE`)."""

    def __init__(self):
        self.lock = threading.Lock()
        self.stores: dict[str, tuple[tuple, object]] = {}
        self.attrs: dict[str, tuple[tuple, object]] = {}
        self.passes: dict[str, _PassState] = {}
        self.plans: dict[MemoryPolicy, MemoryPlan] = {}
        self.cache = TileCache(0)

    def _opened(self, table: dict, path: str, opener):
        """``opener(path)`` once per version of the root zarr.json at ``path``."""
        ident = _identity(path)
        with self.lock:
            held = table.get(path)
            if held is not None and held[0] == ident:
                return held[1]
        value = opener(path)
        with self.lock:
            table[path] = (ident, value)
        return value

    def store(self, path: str):
        """The store at ``path``, opened once per version."""
        return self._opened(self.stores, path, open_store)

    def store_attrs(self, path: str):
        """The attributes of the store at ``path`` (for its writers)."""
        return self._opened(self.attrs, path, read_store_attrs)

    def plan(self, policy: MemoryPolicy, worker=None) -> MemoryPlan:
        """This process's memory plan for ``policy``, made on first use from the limit
        and threads of ``worker`` (a dask worker; by default the one running this, if
        any)."""
        with self.lock:
            plan = self.plans.get(policy)
        if plan is None:
            limit, threads = (_process_limits(policy) if worker is None
                              else _worker_limits(worker, policy))
            plan = plan_memory(limit, threads, policy.n_cols, policy.max_row_nnz)
            with self.lock:
                plan = self.plans.setdefault(policy, plan)
        return plan

    def install_plan(self, policy: MemoryPolicy, plan: MemoryPlan) -> None:
        """Use ``plan`` for ``policy`` here (the local scheduler plans in the caller)."""
        with self.lock:
            self.plans[policy] = plan

    def pass_state(self, spec: PassSpec) -> _PassState:
        """The shared items of ``spec``'s pass in this process."""
        with self.lock:
            state = self.passes.get(spec.pass_id)
            if state is not None:
                return state
            state = self.passes[spec.pass_id] = _PassState()
            stale = [self.passes.pop(k) for k in list(self.passes)[:-_MAX_PASSES]]
        for old in stale:
            old.release()
        return state

    def end(self, pass_id: str | None = None, forget=()) -> None:
        """Let go of a pass's shared items (every pass's when None), and of the cached
        rows and open stores of stores now gone or under the paths ``forget``."""
        with self.lock:
            keys = list(self.passes) if pass_id is None else [pass_id]
            ended = [self.passes.pop(k) for k in keys if k in self.passes]
        for state in ended:
            state.release()
        if pass_id is None:  # the run is over: the kernel's workspaces go too
            release_workspaces()
        forget = tuple(str(p) for p in forget)

        def gone(path) -> bool:
            if bool(forget) and str(path).startswith(forget):
                return True
            # a bucket is not asked about every cached store: those go with ``forget``
            return not is_url(path) and not os.path.exists(path)

        self.cache.drop_where(gone)
        with self.lock:
            for table in (self.stores, self.attrs):
                for path in [p for p in table if gone(p)]:
                    del table[path]


STATE = _ProcessState()


def _process_limits(policy: MemoryPolicy) -> tuple[int | None, int]:
    """(memory limit, threads) of this process: a dask worker's own, capped by the
    policy's limit; else the policy's."""
    distributed = sys.modules.get("distributed")
    if distributed is None:  # a dask worker has it loaded; importing it costs ~0.5 s
        return policy.limit, policy.threads
    try:
        worker = distributed.get_worker()
    except ValueError:
        return policy.limit, policy.threads
    return _worker_limits(worker, policy)


def _worker_limits(worker, policy: MemoryPolicy) -> tuple[int | None, int]:
    own = getattr(getattr(worker, "memory_manager", None), "memory_limit", None) or None
    limits = [x for x in (own, policy.limit) if x]
    return (min(limits) if limits else None), int(worker.state.nthreads)


def plan_on_worker(policy: MemoryPolicy, dask_worker=None) -> MemoryPlan:
    """The memory plan of the worker this runs on (``Client.run`` passes
    ``dask_worker``); cached for its tasks."""
    return STATE.plan(policy, dask_worker)


def end_pass(pass_id: str | None = None, forget=()) -> None:
    """Run on every process after a pass (:meth:`_ProcessState.end`)."""
    STATE.end(pass_id, forget)


def tile_row_keeper(T_path: str, policy: MemoryPolicy):
    """``keep(i, row)``: T's tile row ``i`` (global columns), read whole before any
    pass (for F's diagonal, by a run whose tasks run in this process), held in this
    process's tile cache while it fits what a mat-vec pass of M may cache
    (:func:`_cache_budget`), so that the first pass to make M's rows (the spectral
    radius's first product, else term 1's) makes them from it instead of reading and
    decoding T again, and lets it go (:meth:`.operators.MOperand.rows`). Returns
    whether it was kept."""
    plan = STATE.plan(policy)
    STATE.cache.resize(_cache_budget(plan, None, MATVEC_BLOCKS_HELD * policy.n_cols * 8))
    T, version = STATE.store(T_path), _identity(T_path)
    return lambda i, row: STATE.cache.admit(t_row_key(T, version, i), row)


def forget_tile_rows(T_path: str) -> None:
    """Let go of T's tile rows :func:`tile_row_keeper` kept, where no pass will take
    them: the run's row blocks are not T's tile rows (a tile size chosen smaller, or
    recorded by an earlier run), so M's rows are read from the store."""
    T, version = STATE.store(T_path), _identity(T_path)
    for i in range(T.grid[0]):
        STATE.cache.discard(t_row_key(T, version, i))


def worker_name() -> str:
    return f"{os.getpid()}@{socket.gethostname()}"


class TaskContext:
    """What a task may touch: its row block, the pass's stores (opened by path), the
    pass's shared vectors, the process's tile cache and memory plan, and the writers
    of its own rows of the output stores. Nothing else.

    Attributes
    ----------
    spec : PassSpec
    block : RowBlock
    start, stop : int, the block's rows
    shared : dict of name -> ndarray (``finv``, ``f``: (n,) for a diagonal F, (n/3, 3, 3)
        blocks for a colour one; ``active`` (n,); ``V`` (n, k))
    plan : MemoryPlan
    """

    def __init__(self, spec: PassSpec, block: RowBlock, shared: dict):
        self.spec = spec
        self.block = block
        self.start, self.stop = block.start, block.stop
        self.shared = shared
        self.plan = STATE.plan(spec.memory)
        self.cache = STATE.cache
        self.dtype = np.dtype(spec.dtype)
        self._pass = STATE.pass_state(spec)
        self.tally = blocks.KernelTally()

    def _cast(self, name: str) -> np.ndarray:
        """Shared vector ``name`` in the pass's dtype, cast once per pass."""
        return self._pass.get(("cast", name), lambda: self.shared[name].astype(self.dtype))

    @property
    def finv(self) -> np.ndarray:
        """F^-1 as shared: (n,) or (n/3, 3, 3) blocks."""
        return self.shared["finv"]

    @property
    def inverse(self) -> BlockDiagonal:
        """F^-1 as a :class:`~bigT.kernels.BlockDiagonal` (diagonal or colour blocks),
        made once per pass in this process."""
        return self._pass.get("inverse", lambda: BlockDiagonal(self.shared["finv"]))

    @property
    def M(self) -> MOperand:
        spec = self.spec
        return self._pass.get("M", lambda: MOperand(
            STATE.store(spec.T), self._cast("finv"), self.shared["active"],
            spec.zero_diagonal, self.cache, spec.first_bounce, _identity(spec.T)))

    def operand(self, name: str) -> StoreOperand:
        """Input ``name`` of the pass (read as diag(F) B when the spec says so), one per
        pass in this process, so its tasks share a whole right factor."""
        path = self.spec.input_path(name)

        def make():
            scale = self._cast("f") if name in self.spec.scaled else None
            return StoreOperand(STATE.store(path), scale, self.cache, _identity(path))

        return self._pass.get(("operand", name), make)

    def identity_rows(self) -> sp.csr_array:
        """This block's rows of D = diag(active)."""
        return blocks.identity_rows(self.start, self.stop, self.spec.n,
                                    self.shared["active"], self.dtype)

    def write(self, name: str, rows: sp.csr_array, keep_from: str | None = None,
              kept_columns=(), kept_nnz=()) -> bool:
        """Write this block's rows of output ``name`` (idempotent: a row already
        complete, e.g. by a task run twice, is left alone); the tiles of input
        ``keep_from`` in ``kept_columns`` (holding ``kept_nnz`` entries each) are
        carried over unchanged (hard-linked), ``rows`` holding nothing in those tile
        columns."""
        path = self.spec.output_path(name)
        keep = None
        if keep_from is not None and len(kept_columns):
            keep = KeptTiles(as_location(self.spec.input_path(keep_from)),
                             tuple(int(j) for j in kept_columns),
                             tuple(int(c) for c in kept_nnz))
        return write_tile_row(path, STATE.store_attrs(path), self.block.index, rows, keep=keep)

    def product(self, left: sp.csr_array, right_name: str, threshold: float):
        """(left @ right pruned, tile products done, pairs skipped): see
        :func:`product_with_stored`."""
        right = self.operand(right_name)
        return product_with_stored(left, right, threshold, self.plan,
                                   _whole_limit(self.plan, right),
                                   self.spec.kernel_threads, self.tally)

    def minus_finv_v(self, V) -> np.ndarray:
        """-F^-1 V, computed once per pass in this process."""
        return self._pass.get("minus_finv_v", lambda: -self.inverse.apply(V))

    def cache_budget(self) -> int | None:
        """The tile cache's budget for this pass: the spec's, when it sets one; none
        (left as it is) for a pass that caches nothing; the plan's share less what a
        whole right factor borrows; for a mat-vec of M, also the factor's share and
        half the tasks', less what its dense blocks take (:func:`_cache_budget`)."""
        spec = self.spec
        if spec.cache_bytes is not None:
            return spec.cache_bytes
        if not spec.cache_tiles:
            return None
        if spec.right is not None:
            return _cache_budget(self.plan, self.operand(spec.right))
        if spec.outputs:
            return self.plan.cache_bytes
        # a mat-vec multiplies by no stored factor: the product kernel's idle workspaces,
        # kept for the next product pass (each spans n columns: 863 MB at 4K), would sit
        # beside its dense blocks and push the pass past the plan (4.15 GiB under a 4 GiB
        # limit at 4K); the next product pass makes them again (~0.3 s each)
        release_workspaces()
        V = self.shared.get("V")
        return _cache_budget(self.plan, None, 0 if V is None else _block_bytes(V, spec.n))

    def stats(self, **fields) -> BlockStats:
        """The task's :class:`BlockStats`, with its products' multiply-adds and kernel
        time."""
        return BlockStats(self.block.index, multiply_adds=self.tally.multiply_adds,
                          kernel_seconds=self.tally.seconds, **fields)


def _whole_limit(plan: MemoryPlan, right: StoreOperand) -> int:
    """Bytes the right factor may take held whole and shared by the process's tasks:
    its own share, or the tile cache's too when it needs more (a factor read in
    batches is re-read for every chunk of output rows, which costs far more than
    rebuilding M's rows from T)."""
    if right.nbytes <= plan.whole_bytes + plan.cache_bytes:
        return max(plan.whole_bytes, right.nbytes)
    return plan.whole_bytes


#: The dense (n, k) blocks alive during a mat-vec pass, as multiples of its V: V, its
#: -F^-1 V, the product gathered, and the caller's (the residual estimate's probes Z,
#: X Z and the product's difference from Z). At 4K (k = 4 probes, float64) each is
#: 265 MB: unplanned, they put a 4 GiB run at 5.4 GiB.
MATVEC_BLOCKS_HELD = 6


def _block_bytes(V: np.ndarray, n: int) -> int:
    """Bytes of the dense blocks a mat-vec with ``V`` (shape (n, k)) holds."""
    k = V.shape[1] if V.ndim == 2 else 1
    return MATVEC_BLOCKS_HELD * n * k * 8


def _cache_budget(plan: MemoryPlan, right: StoreOperand | None, blocks_bytes: int = 0) -> int:
    """The tile cache's budget during a pass: its share, less what a whole right
    factor borrows from it; a pass without a right factor (a mat-vec) may also use the
    factor's share and half the tasks', less ``blocks_bytes``, its dense blocks'
    (:data:`MATVEC_BLOCKS_HELD`); never below nothing."""
    if right is None:
        spare = plan.cache_bytes + plan.whole_bytes + plan.threads * plan.work_bytes_per_task // 2
        return max(0, spare - int(blocks_bytes))
    borrowed = max(0, right.nbytes - plan.whole_bytes) if right.nbytes <= (
        plan.whole_bytes + plan.cache_bytes) else 0
    return plan.cache_bytes - borrowed


def product_with_stored(left: sp.csr_array, right: StoreOperand, threshold: float,
                        plan: MemoryPlan, whole_limit: int, kernel_threads: int = 1,
                        tally: blocks.KernelTally | None = None):
    """``left @ right`` pruned at ``threshold``, ``right`` a stored operand (read whole
    or in batches of its tile rows); only tile pairs with both factors nonzero count
    (and are read).

    The right factor is read whole, once per pass and shared by the process's tasks,
    when it fits ``whole_limit``; else the tile rows this product needs, in batches of
    at most a third of the task's work share, multiplied against chunks of the output
    rows (:func:`~.blocks.row_product_batched`). ``tally`` counts the kernel's
    multiply-adds and time.

    Returns
    -------
    (csr_array of left's shape, int tile products, int pairs skipped)
    """
    use, skipped = needed_rows(left, right)
    if not len(use):
        return blocks.empty(left.shape, left.dtype), 0, skipped
    if right.nbytes <= whole_limit:
        out = blocks.row_product(left, right.whole(), threshold, kernel_threads, tally)
        return out, len(use), skipped
    batch_bytes = max(plan.work_bytes_per_task // 3, 1)
    groups, cur, cur_bytes = [], [], 0
    for j in use:
        if cur and cur_bytes + right.row_bytes(j) > batch_bytes:
            groups.append(cur)
            cur, cur_bytes = [], 0
        cur.append(int(j))
        cur_bytes += right.row_bytes(j)
    groups.append(cur)
    batches = [lambda js=js: right.assembled(js) for js in groups]
    partial = max((plan.work_bytes_per_task - batch_bytes) // PARTIAL_BYTES_PER_ENTRY, 1)
    out = blocks.row_product_batched(left, batches, threshold, right.work_per_row(left),
                                     partial, kernel_threads, tally)
    return out, len(use), skipped


def _already_written(spec: PassSpec, block: RowBlock) -> BlockStats | None:
    """Stats read from the row markers when every output row of ``block`` is complete
    (a task the scheduler reruns after losing its worker, or its result): nothing is
    recomputed. None when a row is still to be written."""
    if not spec.outputs:
        return None
    nnz = {}
    for name, path in spec.outputs:
        marker = row_marker(as_location(path), block.index)
        if marker is None:
            return None
        nnz[name] = int(sum(marker["tile_nnz"]))
    first = nnz.get("P", nnz.get("R", 0))
    return BlockStats(block.index, nnz_P=first, nnz_X=nnz.get("X", 0))


def run_block(spec: PassSpec, block: RowBlock, shared: dict) -> BlockStats:
    """The task: run ``spec.task`` on ``block`` in this process.

    Raises
    ------
    BigTError
        bigT's own errors, as raised (a full disk, a damaged store).
    TaskError
        Any other failure, on one line naming the pass, the rows and the cause.
    """
    if task_hook is not None:
        task_hook(spec.op, block.index)
    t0, io0, shared0 = time.perf_counter(), thread_io(), shared_read_bytes()
    done = _already_written(spec, block)
    if done is not None:
        return _measured(done, t0, io0, shared0)
    try:
        ctx = TaskContext(spec, block, shared)
        budget = ctx.cache_budget()
        if budget is not None:
            ctx.cache.resize(budget)
        stats = spec.task(ctx)
        plan, ctx = ctx.plan, None
        # the task's temporaries back to the system once the next task's share would not
        # fit beside what the process holds: else glibc's heap keeps them resident, and a
        # term of many tasks outgrows the plan (4K corner); below it the next task reuses
        # them (MemoryPlan.trim_above)
        return_freed_memory_above(plan.trim_above)
    except BigTError:
        raise
    except OSError as exc:
        if exc.errno == 28:  # ENOSPC
            raise DiskFullError(f"disk full in {spec.op} (term {spec.term}, rows "
                                f"{block.start}:{block.stop}); finished rows are kept",
                                exc.filename or spec.T) from None
        raise TaskError(f"{spec.op} (term {spec.term}, rows {block.start}:{block.stop}) "
                        f"failed: {type(exc).__name__}: {exc}", spec.T) from None
    except MemoryError:
        raise TaskError(f"{spec.op} (term {spec.term}, rows {block.start}:{block.stop}) ran "
                        "out of memory: give the workers more memory or a {option} "
                        "the plan can keep", spec.T, option="memory_limit") from None
    except Exception as exc:
        raise TaskError(f"{spec.op} (term {spec.term}, rows {block.start}:{block.stop}) "
                        f"failed: {type(exc).__name__}: {exc}", spec.T) from None
    return _measured(stats, t0, io0, shared0)


def _measured(stats: BlockStats, t0: float, io0, shared0: int) -> BlockStats:
    """``stats`` with what the task cost since ``time.perf_counter()`` was ``t0``, its
    thread's I/O was ``io0`` and its shared reads ``shared0`` (:mod:`.costs`)."""
    io = thread_io().minus(io0)
    return stats.replace(seconds=time.perf_counter() - t0, worker=worker_name(),
                         bytes_read=io.read_bytes, bytes_written=io.written_bytes,
                         read_calls=io.read_calls, write_calls=io.write_calls,
                         bytes_read_shared=shared_read_bytes() - shared0,
                         resident_bytes=resident_bytes())


def run_mapped_block(block: RowBlock, *, spec: PassSpec, shared: dict) -> BlockStats:
    """:func:`run_block` with the block first (``Client.map`` maps the first argument)."""
    return run_block(spec, block, shared)
