"""The series in memory, when T and the terms fit the memory budget: the same passes
and kernels as the out-of-core path, on whole CSR matrices held by the process instead
of row blocks read from the term stores by dask tasks.

Why: on a small T the products are cheap, and what a run pays once (a dask graph per
pass and per mat-vec, a store read per tile row and per task, the probes' and the
spectral radius's passes over M) costs more than they do (issue #30: the 5120-patch
Cornell box, Fig. 6(a) of the paper). Here M = D - T F^-1 is made once from T's rows
(:func:`bigT.schedule.blocks.m_rows`, as the tasks make each tile row of it), the
products are :func:`bigT.schedule.blocks.row_product` (the pruning spgemm kernel) on
all rows at once, and the sums the tasks' :func:`bigT.kernels.add_diag_scaled` and
:meth:`bigT.kernels.BlockDiagonal.scale_rows`. Every decision is per entry, so a
term's X equals the out-of-core path's (its pruning decisions are the same; only the
order of the residual estimate's sums may differ).

What stays the same: every term published is written into the versioned inverse store
(each of its pass's output stores, a tile row at a time through
:func:`bigT.storage.write_tile_row`, then finalized) and published by the engine with
the same record, so a run may stop anywhere and resume on either path. What the engine
does not publish (a term it goes past within ``PUBLISH_INTERVAL_SECONDS`` of the last
one published, :mod:`.engine`) is computed the same and never written; its outputs are
kept until the term after it is accepted, or written when the engine asks
(:meth:`ResidentPasses.write_term`). The path is
chosen by :func:`choose_path` (``stratified_inverse(..., in_memory=None)``) and
recorded per term (``engine_path`` of the history, docs/FORMAT.md); before each term
the engine asks :meth:`ResidentPasses.fits` and goes on out of core when the next
term's predicted size does not fit the budget.
"""

from __future__ import annotations

import time
from concurrent.futures import Future, wait
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..kernels import BlockDiagonal, prune, scale_rows, spmm_dense, workspace_bytes
from ..kernels.row_ranges import (narrow_columns, prune_rows, restrict_to_used_rows,
                                  row_view, scaled_off_diagonal_rows, stack_rows,
                                  tile_pairs)
from ..kernels.threads import map_all, shared_pool
from ..schedule import blocks
from ..schedule.memory import stored_bytes
from ..schedule.operators import StoreOperand, largest_row_entries
from ..schedule.spec import BlockStats, row_blocks
from ..storage import InverseStore, StoreAttrs, completed_rows, write_tile_row
from ..storage import open as open_store
from .engine_path import IN_MEMORY
from .methods import Pass, SeriesMethod
from .passes import PassTotals, term_store_attrs

#: The term held, the term made and the product's unpruned rows alive at once: the
#: predicted bytes of a term are this many times the held term's X and P (grown as the
#: last term grew X).
TERM_COPIES = 3


class ResidentMatrices:
    """M and the terms' matrices held by the process.

    Parameters
    ----------
    layout : RunLayout
    store : InverseStore
        Where a term not held (a resumed store's) is read from.
    threads : int
        Threads of the element-wise kernels (:meth:`prune`).

    Attributes
    ----------
    M : csr_array, shape (n, n)
        D - T F^-1 in T's dtype, as the tasks make it (:func:`bigT.schedule.blocks.m_rows`).
    """

    def __init__(self, layout, store: InverseStore, threads: int = 1):
        self.layout, self.store, self.threads = layout, store, max(1, int(threads))
        self.dtype = np.dtype(layout.T.dtype)
        self.M = self._make_M()
        self._operator: tuple[float, sp.csr_array] | None = None
        self.held: dict[tuple[str, int], sp.csr_array] = {}

    @property
    def n(self) -> int:
        return self.layout.n

    def _make_M(self) -> sp.csr_array:
        """M, shape (n, n), sorted: each tile row of T made into M's rows as a task makes
        them (:func:`bigT.schedule.blocks.m_rows`). T's rows are those the run set-up
        read for F (``layout.T_rows``, let go of here), else read here, ``threads`` at
        once (a read decodes, checks and joins the row's tiles, mostly in numpy and
        numba, which let go of the interpreter). A grey M with F = diag T is written
        straight into its arrays (:func:`~bigT.kernels.row_ranges.scaled_off_diagonal_rows`:
        the same entries without a block per tile row, nor stacking them on one
        thread); otherwise, or where T's rows are not as its reader checks them,
        ``threads`` tile rows at once, then the rows stacked (one copy)."""
        lay = self.layout
        finv = lay.fb.finv.astype(self.dtype)
        T_row = lay.T.get_tile_row if lay.T_rows is None else lay.T_rows.take
        pool = shared_pool("M", self.threads)
        rows = map_all(pool, T_row, range(lay.T.grid[0]))
        starts = [lay.T.tile_row_range(i)[0] for i in range(lay.T.grid[0])]
        if lay.fb.channels == 1 and lay.fb.zero_diagonal:
            M = scaled_off_diagonal_rows(rows, starts, -finv, self.threads)
            if M is not None:
                return M

        def m_block(i: int) -> sp.csr_array:  # T's tile row i (its tiling, not X's)
            start, stop = lay.T.tile_row_range(i)
            T_rows, rows[i] = rows[i], None  # let go of as its rows of M are made
            return blocks.m_rows(T_rows=T_rows, start=start, finv=finv,
                                 active_rows=lay.fb.active[start:stop],
                                 zero_diagonal=lay.fb.zero_diagonal)

        M = stack_rows(map_all(pool, m_block, range(lay.T.grid[0])))
        M.has_sorted_indices = True
        return M

    def M_pruned(self, threshold: float | None) -> sp.csr_array:
        """M with its entries below ``threshold`` left out (the power form's operator
        threshold), made once."""
        if threshold is None:
            return self.M
        if self._operator is None or self._operator[0] != threshold:
            self._operator = (threshold, self.prune(self.M, threshold))
        return self._operator[1]

    def prune(self, A: sp.csr_array, threshold: float) -> sp.csr_array:
        """:func:`bigT.kernels.prune` of A, shape (n, n), on the threads' row ranges."""
        return prune_rows(A, threshold, self.threads)

    def term(self, name: str, k: int) -> sp.csr_array:
        """Store ``name`` of term ``k``, held, or read whole from the store (a resumed
        run's first term)."""
        key = (name, k)
        if key not in self.held:
            stored = StoreOperand(open_store(self.store.term_path(k, name)))
            self.held[key] = stored.whole()
        return self.held[key]

    def keep(self, name: str, k: int, A: sp.csr_array) -> None:
        self.held[(name, k)] = A

    def forget_before(self, k: int) -> None:
        """Let go of the matrices of terms before ``k`` (published over, or dropped)."""
        for key in [key for key in self.held if key[1] < k]:
            del self.held[key]

    def bytes_held(self) -> int:
        """Bytes of M, its pruned copy and the terms held."""
        mats = [self.M, *self.held.values()]
        if self._operator is not None:
            mats.append(self._operator[1])
        return sum(A.data.nbytes + A.indices.nbytes + A.indptr.nbytes for A in mats)


@dataclass(frozen=True, eq=False)
class ResidentMatVecs:
    """:class:`~.matvecs.MatVecs` in memory: products with the held M and X."""

    matrices: ResidentMatrices
    threads: int = 1

    @property
    def layout(self):
        return self.matrices.layout

    def apply_M(self, V: np.ndarray, largest: bool = False) -> np.ndarray:
        """M V, shape (n, p); with ``largest``, each row's largest entry of M (0 for a
        row without a positive one), shape (n, 1)."""
        M = self.matrices.M
        if largest:
            return largest_row_entries(M)
        return self._product(M, V)

    def apply_abs_M(self, V: np.ndarray) -> np.ndarray:
        """|M| V, shape (n, p)."""
        return self._product(self.matrices.M, V, absolute=True)

    def m_nonpositive(self) -> bool:
        """Whether M has no positive entry: known from T's rows that gave F
        (:attr:`.first_bounce.FirstBounce.m_nonpositive`), else read from M."""
        if self.layout.fb.m_nonpositive:
            return True
        return bool(self.matrices.M.data.max(initial=0.0) <= 0.0)

    def apply_X(self, X, V: np.ndarray) -> np.ndarray:
        """X V, shape (n, p), for the term store ``X`` (held, else read), or for X held
        (a csr_array: a term not written yet)."""
        if sp.issparse(X):
            return self._product(X, V)
        held = {str(self.matrices.store.term_path(k, name)): A
                for (name, k), A in self.matrices.held.items() if name == "X"}
        A = held.get(str(X.path))
        return self._product(StoreOperand(X).whole() if A is None else A, V)

    def _product(self, A: sp.csr_array, V: np.ndarray, absolute: bool = False) -> np.ndarray:
        V = np.ascontiguousarray(V)
        out = np.zeros((A.shape[0], V.shape[1]),
                       dtype=np.result_type(V.dtype, A.dtype, np.float32))
        spmm_dense(A, V, out=out, n_threads=self.threads, absolute=absolute)
        return out


@dataclass(frozen=True)
class _Result:
    """What one pass computed.

    Attributes
    ----------
    outputs : dict of str to csr_array, shape (n, n)
        The pass's outputs by store name; ``"_new"``, where the term's new rows are no
        output (Horner's M S, term 0's F^-1), only for the stats' ``nnz_P``.
    left, right : csr_array or None
        The factors of its product (the stats count their tile pairs).
    y : (n, p) ndarray or None
        The probes' (X_k - X_{k-1}) Z (the power form).
    carried_from_P : bool
        A product with P_{k-1}: a row block it left without any is carried over.
    """

    outputs: dict
    left: sp.csr_array | None = None
    right: sp.csr_array | None = None
    y: np.ndarray | None = None
    carried_from_P: bool = False


class ResidentPasses:
    """:class:`~.passes.PassRunner` in memory: each pass of the series computed on whole
    matrices, its outputs written into the term's stores and kept for the next term.

    Parameters
    ----------
    matrices : ResidentMatrices
    store : InverseStore
    settings : SeriesSettings
    probes : (n, p) ndarray, the residual probes Z, or None where the run estimates no
        residual (then no pass reports (X_k - X_{k-1}) Z)
    threads : int, threads of the kernels and of the writes
    budget : int, bytes the matrices may take (:meth:`fits`)
    series : SeriesMethod, optional
        Given, the next term of a one-pass method is computed ahead (:meth:`_ahead`).

    A pass's outputs are written on a thread of their own (:meth:`run`): the engine
    estimates the term's residual meanwhile (from the probes' X Z carried, without
    reading X), and :attr:`finalized` waits for the writes before it hands the stores
    over. While a term's stores are written (mostly waiting on the disk's syncs), the next
    term's products are computed on another thread: the engine publishes the term
    written, then takes the next one's result. Only where nothing may stop the run
    between two terms but ``terms`` itself (no ``on_term``), so that no product is
    made for nothing; its matrices are only kept (and written) once the engine asks
    for that term.
    """

    def __init__(self, matrices: ResidentMatrices, store: InverseStore, settings,
                 probes: np.ndarray, threads: int, budget: int,
                 series: SeriesMethod | None = None):
        self.matrices, self.store, self.settings = matrices, store, settings
        self.layout = matrices.layout
        self.probes, self.threads, self.budget = probes, max(1, int(threads)), budget
        self.series = series
        self.totals = PassTotals()
        self._finalized: dict[tuple[int, str], object] = {}  # :attr:`finalized`
        self._inverse = BlockDiagonal(self.layout.fb.finv)
        self._f = self.layout.fb.f.astype(matrices.dtype)
        self._next: tuple[str, int, Future] | None = None
        self._dropped: list[Future] = []  # terms ahead not asked for, waited for by close
        # the outputs of the passes of terms computed and not written, by term
        self._unwritten: dict[int, list[tuple[Pass, dict]]] = {}
        # the threads (the process's, started once: ~3 ms a thread, issue #30) of the
        # writes, of the passes' writes in flight (one after the other on the thread
        # that drives them, which waits on the writes') and of the term ahead
        self._writers = shared_pool("write", self.threads)
        self._writing: list[Future] = []
        self._writer = shared_pool("write-pass", 1)
        self._pool = shared_pool("ahead", 1)

    @property
    def finalized(self) -> dict[tuple[int, str], object]:
        """The stores the passes wrote and finalized, opened, by (term, name), as
        :class:`~.passes.PassRunner`'s: the writes in flight waited for first (a write
        that failed raises its error here)."""
        writing, self._writing = self._writing, []
        for future in writing:
            future.result()
        return self._finalized

    def close(self) -> None:
        """Wait for a term computed ahead (its result is dropped; not started, it is
        cancelled) and the writes (each write waits for its own row writes,
        :func:`~bigT.kernels.threads.map_all`): the pools are the process's, so
        nothing of this run is left running on them."""
        if self._next is not None:
            self._dropped.append(self._next[2])
        self._next = None
        for future in self._dropped:
            future.cancel()
        wait(self._dropped)
        self._dropped = []
        for future in self._writing:  # their errors, if any, are the engine's to raise
            future.exception()
        self._writing = []

    # --- the engine's questions -------------------------------------------------------

    def fits(self, held: int, nnz_X: int, nnz_P: int, growth: float) -> bool:
        """Whether the term after ``held`` (X holding ``nnz_X`` entries, P ``nnz_P``,
        X grown ``growth`` times at the last term) fits the budget."""
        lay = self.layout
        itemsize = self.matrices.dtype.itemsize
        grow = max(1.0, growth)
        terms = TERM_COPIES * grow * (stored_bytes(nnz_X, lay.n, itemsize)
                                      + stored_bytes(nnz_P, lay.n, itemsize))
        M = self.matrices.M
        fixed = 2 * stored_bytes(M.nnz, lay.n, itemsize) + self.threads * workspace_bytes(
            lay.n, lay.n)
        return fixed + terms <= self.budget

    def warn_row_width(self, held, k, history) -> None:
        """Nothing to warn about: :meth:`fits` decides before each term."""

    def exhausted_before(self, series: SeriesMethod, p: Pass, held: int) -> str | None:
        """:func:`.passes.exhausted_before` on the matrices held (``exhausted`` reads only
        their entry count)."""
        for _alias, name, term in p.inputs:
            reason = series.exhausted(held, name, self.matrices.term(name, term))
            if reason:
                return reason
        return None

    # --- a pass -----------------------------------------------------------------------

    def run(self, p: Pass, k: int, metadata: dict, write: bool = True) -> list[BlockStats]:
        """Compute pass ``p`` of term ``k`` in memory, write its outputs into the term's
        stores (:meth:`_write`; without ``write``, later by :meth:`write_term`, or
        never) and keep them; returns one BlockStats per row block (as the out-of-core
        tasks report, so the engine's probes and records read them the same way)."""
        t0 = time.perf_counter()
        ahead, self._next = self._next, None
        if ahead is not None and ahead[:2] == (p.op, k):
            result, tally = ahead[2].result()
        else:
            if ahead is not None:  # not this pass: dropped (close waits for it)
                ahead[2].cancel()
                self._dropped.append(ahead[2])
            tally = blocks.KernelTally()
            result = self._compute(p, self._inputs(p), tally)
        # the outputs of the held term's passes stay until the term after them is made
        self.matrices.forget_before(min((term for _a, _n, term in p.inputs), default=k))
        for name in p.outputs:
            self.matrices.keep(name, k, result.outputs[name])
        self._ahead(p, k)
        if write:
            self._writing.append(self._writer.submit(self._write, k, p, result.outputs,
                                                     metadata))
        else:
            self._unwritten.setdefault(k, []).append((p, result.outputs))
        stats = self._stats(p, result, tally, time.perf_counter() - t0)
        self.totals = self.totals.plus(time.perf_counter() - t0, stats, 1)
        return stats

    def write_term(self, k: int, metadata: dict, inverse: dict | None = None):
        """Write the outputs of term ``k``'s passes that :meth:`run` left unwritten
        into the term's stores; returns its X store, finalized (with ``inverse``, the
        metadata publishing it records, in the same write:
        :meth:`bigT.storage.InverseStore.finalize_term_store`)."""
        finalized = self.finalized  # the writes in flight done first: they share its pool
        for p, outputs in self._unwritten.pop(k, []):
            self._write(k, p, outputs, metadata, inverse)
        return finalized.pop((k, "X"))

    def forget_unwritten(self, before: int) -> None:
        """Let go of the unwritten outputs of the terms before ``before`` (a later term
        was accepted: they are never published)."""
        for k in [k for k in self._unwritten if k < before]:
            del self._unwritten[k]

    def _inputs(self, p: Pass) -> dict:
        return {alias: self._input(alias, name, term, p) for alias, name, term in p.inputs}

    def _ahead(self, p: Pass, k: int) -> None:
        """Start computing the term after ``k`` on the pool's thread when the run will
        ask for it (a one-pass method, ``k`` short of ``terms``, no ``on_term``, the
        series not exhausted) and it fits the budget."""
        series, settings = self.series, self.settings
        if series is None or settings.on_term is not None or p.op == "diag":
            return
        k_next = series.next_term(k)
        passes = series.passes(k, k_next)
        if k_next > settings.terms or len(passes) != 1:
            return
        q = passes[0]
        if self.exhausted_before(series, q, k):
            return
        X, P = self.matrices.held.get(("X", k)), self.matrices.held.get(("P", k))
        if X is None or not self.fits(k, X.nnz, 0 if P is None else P.nnz, 1.0):
            return
        inputs = self._inputs(q)  # resolved now: the held matrices change on this thread

        def compute():
            tally = blocks.KernelTally()
            return self._compute(q, inputs, tally), tally

        self._next = (q.op, k_next, self._pool.submit(compute))

    def _input(self, alias: str, name: str, term: int, p: Pass) -> sp.csr_array:
        """Input ``alias`` of the pass, read as F B when the pass scales it (S = F X)."""
        A = self.matrices.term(name, term)
        if alias not in p.scaled:
            return A
        if self._f.ndim == 3:
            return BlockDiagonal(self._f).scale_rows(A, 0)
        return scale_rows(A, self._f)

    def _compute(self, p: Pass, inputs: dict, tally) -> _Result:
        return {"diag": self._diag, "power": self._power, "horner": self._horner,
                "ns-residual": self._ns_residual,
                "ns-update": self._ns_update}[p.op](inputs, tally)

    def _product(self, left: sp.csr_array, right: sp.csr_array, threshold: float,
                 tally) -> sp.csr_array:
        """left @ right pruned at ``threshold``, shapes (n, n): on the right factor's
        columns that hold entries when they are few (:func:`narrow_columns`: the same
        entries, in less of the kernel's accumulators), with the left factor's entries
        that meet an empty row of the right one left out when they are many
        (:func:`restrict_to_used_rows`)."""
        restricted = restrict_to_used_rows(left, right, self.threads)
        if restricted is not None:
            left = restricted
        narrowed = narrow_columns(right, self.threads)
        if narrowed is None:
            return blocks.row_product(left, right, threshold, self.threads, tally)
        product = blocks.row_product(left, narrowed.matrix, threshold, self.threads, tally)
        return narrowed.widen(product, self.threads)

    def _identity(self) -> sp.csr_array:
        return blocks.identity_rows(0, self.layout.n, self.layout.n, self.layout.fb.active,
                                    self.matrices.dtype)

    def _x_of(self, S: sp.csr_array) -> sp.csr_array:
        """X = F^-1 S, explicit zeros dropped (the tasks' ``_x_rows``)."""
        X = self._inverse.scale_rows(sp.csr_array(S), 0, self.matrices.dtype)
        X.eliminate_zeros()
        return X

    def _diag(self, inputs, tally) -> _Result:
        X = self._inverse.rows(0, self.layout.n, self.matrices.dtype)
        return _Result({"X": X, "_new": X})

    def _power(self, inputs, tally) -> _Result:
        """The power task on all rows: Q_k = (M P_{k-1}) pruned, X_k = X_{k-1} +
        F^-1 Q_k, P_k = Q_k pruned at the feed threshold (methods.power_task)."""
        th = self.settings.thresholds
        mats = self.matrices
        left = right = None
        if "P" in inputs:
            left, right = mats.M_pruned(th.operator), inputs["P"]
            Q = self._product(left, right, th.prune, tally)
        else:
            Q = mats.prune(mats.M, th.prune)
        feed = th.prune if th.feed is None else th.feed
        P = mats.prune(Q, feed) if feed > th.prune and Q.nnz else Q
        X_prev = inputs["X"]
        if not Q.nnz:
            X = X_prev
        elif self._inverse.b == 1:
            X = blocks.add_scaled(X_prev, self.layout.fb.finv, Q, self.threads)
        else:
            X = sp.csr_array(X_prev + self._inverse.scale_rows(Q, 0, mats.dtype))
            X.eliminate_zeros()
            X.sort_indices()
        y = None  # no residual estimated: no probes (the engine's ``needs_residual``)
        if self.probes is not None:
            y = np.zeros((self.layout.n, self.probes.shape[1]), np.float64)
        if Q.nnz and y is not None:
            spmm_dense(Q, self.probes, out=y, n_threads=self.threads)
            y = self._inverse.apply(y, 0)
        return _Result({"P": P, "X": X}, left, right, y, carried_from_P="P" in inputs)

    def _horner(self, inputs, tally) -> _Result:
        """S_n = D + (M S_{n-1}) pruned, X_n = F^-1 S_n (methods.horner_task)."""
        S = inputs["S"]
        MS = self._product(self.matrices.M, S, self.settings.thresholds.prune, tally)
        # "_new": the term's new rows, counted as the task's nnz_P; not an output
        return _Result({"X": self._x_of(self._identity() + MS), "_new": MS},
                       self.matrices.M, S)

    def _ns_residual(self, inputs, tally) -> _Result:
        """R = (D - S + M S) pruned (methods.ns_residual_task)."""
        S = inputs["S"]
        MS = self._product(self.matrices.M, S, 0.0, tally)
        R = prune(sp.csr_array(self._identity() - S + MS),
                  threshold=self.settings.thresholds.prune)
        return _Result({"R": R}, self.matrices.M, S)

    def _ns_update(self, inputs, tally) -> _Result:
        """S' = S + (S R) pruned, X' = F^-1 S' (methods.ns_update_task)."""
        S, R = inputs["S"], inputs["R"]
        SR = self._product(S, R, self.settings.thresholds.prune, tally)
        return _Result({"X": self._x_of(S + SR)}, S, R)

    # --- writing and counting ---------------------------------------------------------

    def _write(self, k: int, p: Pass, outputs: dict, metadata: dict,
               inverse: dict | None = None) -> None:
        """Each output of pass ``p`` into its store of term ``k``: created (or the
        rows an interrupted run left kept), its tile rows written, finalized; each
        step for every output at once on the run's threads (a store write waits mostly
        on the disk's syncs, which release the interpreter)."""
        lay = self.layout
        attrs = term_store_attrs(lay, k, metadata)
        names, pool = list(p.outputs), self._writers
        paths = map_all(pool, lambda name: self.store.prepare_term_store(k, name, attrs),
                        names)
        rows = []
        for name, path in zip(names, paths):
            done = completed_rows(path, lay.n_blocks)
            rows += [(path, b, outputs[name]) for b in row_blocks(lay.n, lay.tile_size)
                     if b.index not in done]
        map_all(pool, lambda job: _write_row(attrs, *job), rows)
        extra = {"X": None if inverse is None else {"inverse": inverse}}
        stores = map_all(pool, lambda name: self.store.finalize_term_store(
            k, name, extra.get(name)), names)
        self._finalized.update({(k, name): X for name, X in zip(names, stores)})

    def _stats(self, p: Pass, result: _Result, tally, seconds: float) -> list[BlockStats]:
        """One BlockStats per row block, as its task would report it: the new term's
        and X's entries, the tile products (pairs of a left tile holding entries and a
        nonempty right tile row), the probes' rows; the kernel's counts on the first."""
        lay = self.layout
        first = result.outputs.get("P", result.outputs.get("R", result.outputs.get("_new")))
        X = result.outputs.get("X")
        computed, skipped = _tile_pairs(result.left, result.right, lay.n_blocks,
                                        lay.tile_size)
        stats = []
        for b in row_blocks(lay.n, lay.tile_size):
            y = None if result.y is None or not p.probed else result.y[b.start:b.stop]
            stats.append(BlockStats(
                b.index, seconds=seconds if b.index == 0 else 0.0, worker=IN_MEMORY,
                nnz_P=_rows_nnz(first, b), nnz_X=_rows_nnz(X, b),
                computed=int(computed[b.index]), skipped=int(skipped[b.index]),
                row_skipped=result.carried_from_P and computed[b.index] == 0, y=y,
                multiply_adds=tally.multiply_adds if b.index == 0 else 0,
                kernel_seconds=tally.seconds if b.index == 0 else 0.0))
        return stats


def _write_row(attrs: StoreAttrs, path, block, A: sp.csr_array) -> None:
    # a view of the rows: the writer checks and copies them itself (a slice would copy
    # every entry of the term once more)
    write_tile_row(path, attrs, block.index, row_view(A, block.start, block.stop))


def _rows_nnz(A: sp.csr_array | None, block) -> int:
    if A is None:
        return 0
    return int(A.indptr[block.stop] - A.indptr[block.start])


def _tile_pairs(left: sp.csr_array | None, right: sp.csr_array | None, n_blocks: int,
                tile_size: int) -> tuple[np.ndarray, np.ndarray]:
    """Per row block of ``left``: the tile rows of ``right`` its product reads and the
    pairs skipped (:func:`bigT.kernels.row_ranges.tile_pairs`, what
    :func:`needed_rows` counts per task), shapes (n_blocks,); zeros without a
    product."""
    if left is None or right is None or not left.nnz:
        return np.zeros(n_blocks, np.int64), np.zeros(n_blocks, np.int64)
    return tile_pairs(left, right, tile_size, n_blocks)
