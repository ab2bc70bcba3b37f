"""The engine of :func:`~bigT.algorithms.stratified_inverse`: one run's loop over terms,
each term's passes handed to the runner, each finished term's residual estimated and
the term published in the inverse store.

A term is published only once it is complete: its stores are written under ``tKKKK``
by the tasks of its passes (each task its own tile rows), its residual is estimated and
recorded in X's metadata, the root's redirect flips to it, the record follows, and the
previous term is deleted. A crash leaves the previous term readable; the same call
resumes at the first incomplete row block of the next term. The order of these writes
is what the crash harness (tests/reliability) checks.

Divergence is refused twice: before term 0, rho(M) is estimated
(:func:`bigT.spectral.spectral_radius`: a Collatz-Wielandt bracket where M = -|M|, as
for any transport without negative entries; else Arnoldi) and the run refused unless
rho + uncertainty < 1; after every term, a residual that grew and exceeds the smallest
so far ``config.RESIDUAL_GROWTH`` times is not published (not any growth: with a
non-normal M, or at the pruning floor, a convergent series may grow for a term).
``force`` skips both.

The tasks run on :mod:`bigT.schedule.runner` (local threads, or a dask cluster's
workers); the term stores take T's tile size, halved until every thread has work
(:func:`choose_tile_size`), recorded and kept on resume.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass

import numpy as np

from .. import config
from ..errors import DivergenceError
from ..schedule.matvec import matvec, matvec_spec
from ..schedule.memory import warn_if_rows_outgrow
from ..schedule.operators import StoreOperand
from ..schedule.runner import ClusterRunner, local_path, new_pass_id
from ..schedule.spec import BlockStats, MemoryPolicy, PassSpec, row_blocks
from ..spectral import SpectralRadius, spectral_radius
from ..storage import InverseStore, StoreAttrs
from ..storage import completed_rows
from ..storage import open as open_store
from ..storage.inverse_store import term_dir
from .fingerprint import inverse_fingerprint
from .first_bounce import resolve_first_bounce
from .methods import TERM_ZERO, Pass, SeriesMethod
from .records import SeriesRecord, TermRecord
from .report import InverseReport
from .residual import estimate_residual, residual_probes
from .settings import SeriesSettings


def choose_tile_size(n: int, tile_size: int, threads: int) -> int:
    """T's tile size, halved while it gives fewer than ``config.TASKS_PER_THREAD`` row
    blocks per thread, halving adds blocks, and blocks keep at least
    ``config.MIN_BLOCK_ROWS`` rows."""
    ts = int(tile_size)
    while (-(-n // ts) < config.TASKS_PER_THREAD * threads and ts // 2 >= config.MIN_BLOCK_ROWS
           and -(-n // (ts // 2)) > -(-n // ts)):
        ts //= 2
    return ts


def max_row_nnz(T) -> int:
    """Entries of T's widest tile row."""
    indptr = np.asarray(T.tile_indptr)
    tile_nnz = np.append(np.asarray(T.tile_nnz, dtype=np.int64), 0)
    row_nnz = np.add.reduceat(tile_nnz, indptr[:-1]) * (np.diff(indptr) > 0)
    return int(row_nnz.max(initial=0))


@dataclass
class PassTiming:
    """Tasks of the product passes and the threads' time not spent inside them:
    (wall time x threads - time in tasks) / tasks is what scheduling a task costs
    (submission, scattering, results, idle threads at the end of a pass)."""

    tasks: int = 0
    thread_seconds: float = 0.0
    task_seconds: float = 0.0

    def add(self, wall: float, stats: list[BlockStats], threads: int) -> None:
        self.tasks += len(stats)
        self.thread_seconds += wall * threads
        self.task_seconds += sum(s.seconds for s in stats)

    def overhead_ms(self) -> float:
        if not self.tasks:
            return 0.0
        return 1e3 * max(0.0, self.thread_seconds - self.task_seconds) / self.tasks


class InverseEngine:
    """One run of :func:`stratified_inverse` on ``T`` into ``store``.

    Parameters
    ----------
    T : BlockCSR, shape (n, n)
    store : InverseStore
        Opened (its writer lock taken) here; the caller closes it.
    series : SeriesMethod
    runner : a runner of :mod:`bigT.schedule.runner`
    settings : SeriesSettings
    first_bounce : what :func:`resolve_first_bounce` takes
    memory_limit : int or None
    """

    def __init__(self, T, store: InverseStore, series: SeriesMethod, runner,
                 settings: SeriesSettings, first_bounce, memory_limit):
        self.T, self.series, self.runner, self.settings = T, series, runner, settings
        self.T_path = local_path(T.path, "transport T")  # as the workers will open it
        runner.check_paths([self.T_path])
        if settings.progress and isinstance(runner, ClusterRunner):
            # a cluster run may be long: where to watch it (the dashboard) comes first
            print(f"bigT: running on {runner.describe()}", file=sys.stderr)
        self.fb = resolve_first_bounce(T, first_bounce)
        self.policy = MemoryPolicy(memory_limit, runner.threads, T.shape[1], max_row_nnz(T))
        self.plans = runner.plans(self.policy)
        self.store = store
        self.created = not store.path.exists() or settings.overwrite
        self.record = self._open_record()
        runner.check_paths([str(store.path)])
        self.tile_size = self._tile_size()
        self.n_blocks = -(-T.shape[0] // self.tile_size)
        self.kernel_threads = (1 if self.n_blocks >= runner.threads
                               else runner.idle_kernel_threads)
        self.shared = {"finv": self.fb.finv, "f": self.fb.f, "active": self.fb.active}
        self.products = 0
        self.timing = PassTiming()
        # the residual probes and X Z for the term held (None: unknown, X is read)
        self.probes = residual_probes(self.fb, seed=settings.seed)
        self.XZ: np.ndarray | None = None

    def _open_record(self) -> SeriesRecord:
        """The store's record: new, or the one held for the same fingerprint."""
        params = inverse_fingerprint(self.T, self.fb, self.settings.thresholds,
                                     self.series.name)
        stored = self.store.open_or_create(params, overwrite=self.settings.overwrite)
        return SeriesRecord.from_stored(stored, self.store.path)

    def _tile_size(self) -> int:
        """The term stores' tile size: recorded by the run that made the store, or
        chosen now for this run's threads (and recorded)."""
        if self.record.tile_size is None:
            ts = choose_tile_size(self.T.shape[0], self.T.tile_size, self.runner.threads)
            self._save(self.record.replace(tile_size=ts, excluded_pixels=self.fb.excluded))
        return self.record.tile_size

    def _save(self, record: SeriesRecord) -> None:
        self.store.save(record.to_stored())
        self.record = record

    # --- the run --------------------------------------------------------------------

    def run(self, t_start: float) -> InverseReport:
        """Estimate rho (refusing a diverging series), compute the terms, report."""
        resumed_from = self.record.term
        try:
            t0 = time.perf_counter()
            rho, computed = self._spectral_radius()
            t_rho = time.perf_counter() - t0
            if self.record.term is None:
                self._term_zero()
        except BaseException:
            # refused (a diverging series) or stopped before any term was finished: an
            # output this run created holds nothing worth keeping
            if self.created and self.record.term is None:
                self.store.discard()
            raise
        try:
            stopped = self._extend(resumed_from)
        finally:
            self.store.settle()
        if self.record.dir is not None:
            self.store.clean(keep={self.record.dir})  # terms readers held when dropped
        return self._report(stopped, resumed_from, t_rho, time.perf_counter() - t_start,
                            rho, computed)

    def _spectral_radius(self) -> tuple[SpectralRadius, bool]:
        """(rho(M), whether this run computed it): estimated once per store (kept in
        the record); a series that may diverge (rho + its uncertainty >= 1) is refused
        unless forced."""
        rec = self.record
        # a record without an uncertainty was made by the older power iteration, which
        # reads low on crowded spectra: estimated again
        computed = rec.spectral_radius is None or rec.spectral_uncertainty is None
        if computed:
            rho = spectral_radius(self._apply_M, self.T.shape[0], self.fb.active,
                                  seed=self.settings.seed, nonpositive=self._m_nonpositive())
            if rho.converged:  # else estimated anew on the next run
                self._save(rec.replace(spectral_radius=rho.value,
                                       spectral_uncertainty=rho.uncertainty,
                                       spectral_products=rho.products,
                                       spectral_method=rho.method))
        else:
            rho = SpectralRadius(rec.spectral_radius, rec.spectral_uncertainty,
                                 rec.spectral_products or 0, rec.spectral_method or "recorded")
        if not rho.upper < 1 and not self.settings.force:
            raise DivergenceError(
                f"the spectral radius of M = I - T F^-1 is {rho.describe()}, so it may be "
                f">= 1 (first bounce {self.fb.kind}): the series diverges. Try the "
                "diagonal first bounce, a higher threshold on T's small entries (or "
                "denoising it), fixing negative or zero diagonal entries, or {option} "
                "to run anyway", self.T.path, option=("force", True))
        return rho, computed

    def _extend(self, resumed_from) -> str:
        """Compute terms until ``terms`` is held, ``tol`` is reached or the series is
        exhausted; returns why it stopped."""
        terms, rec, on_term = self.settings.terms, self.record, self.settings.on_term
        if rec.exhausted_at is not None and rec.term < terms:
            self._save(rec.replace(term=terms))
            return f"series exhausted at term {rec.exhausted_at}"
        computed = False
        if resumed_from is not None and on_term and self.record.term < terms:
            # the term held may already be enough: the callback sees it before any work
            reason = on_term(self.record)
            if reason:
                return reason
        while self.record.term < terms:
            if self._tol_reached():
                return f"tol {self.settings.tol:g} reached"
            computed = True
            reason = self._next_term() or (on_term(self.record) if on_term else None)
            if reason:
                return reason
        if self._tol_reached():
            return f"tol {self.settings.tol:g} reached"
        if resumed_from is not None and not computed:
            return f"already held term {self.record.term}"
        return "terms reached"

    def _tol_reached(self) -> bool:
        tol, residual = self.settings.tol, self.record.residual
        return tol is not None and residual is not None and residual <= tol

    def _term_zero(self) -> None:
        self.store.clean(keep={0})
        t0 = time.perf_counter()
        stats = self._run_pass(TERM_ZERO, 0)
        self._finish_term(0, stats, t0, XZ=self.fb.finv[:, None] * self.probes)

    def _next_term(self) -> str | None:
        """Compute the term after the one held and publish it; a reason when the series
        turns out exhausted instead."""
        held = self.record.term
        k = self.series.next_term(held)
        self._warn_row_width(held, k)
        self.store.clean(keep={held, k})
        t0 = time.perf_counter()
        stats = []
        for p in self.series.passes(held, k):
            reason = self._exhausted(p, held)
            if reason:
                self._save(self.record.replace(term=self.settings.terms, exhausted_at=held))
                return reason
            stats += self._run_pass(p, k)
        self._finish_term(k, stats, t0, XZ=self._updated_XZ(stats))
        # the caches let go of the held term first: their open stores hold its lease
        self.runner.end_pass(None, forget=(str(self.store.path / term_dir(held)),))
        # deleted while the next term computes; the run waits for it before it returns
        self.store.drop_term(held, background=True)
        return None

    def _updated_XZ(self, stats: list[BlockStats]) -> np.ndarray | None:
        """X_k Z, shape (n, p), from X_{k-1} Z and every row block's
        (X_k - X_{k-1}) Z, when the term's tasks all reported theirs (the power form's
        do); else None."""
        if (self.XZ is None or len(stats) != self.n_blocks
                or any(s.y is None for s in stats)):
            return None
        XZ = self.XZ.copy()
        for s in stats:
            start = s.index * self.tile_size
            XZ[start:start + s.y.shape[0]] += s.y
        return XZ

    def _exhausted(self, p: Pass, held: int) -> str | None:
        for _alias, name, term in p.inputs:
            reason = self.series.exhausted(held, name, open_store(self.store.term_path(term, name)))
            if reason:
                return reason
        return None

    # --- passes ---------------------------------------------------------------------

    def _run_pass(self, p: Pass, k: int) -> list[BlockStats]:
        """Create (or resume) the pass's output stores, run a task per row block not yet
        complete in all of them, finalize them from their row markers."""
        paths = {name: self.store.prepare_term_store(k, name, self._term_attrs(k))
                 for name in p.outputs}
        done = [set(completed_rows(path, self.n_blocks)) for path in paths.values()]
        todo = [i for i in range(self.n_blocks) if any(i not in d for d in done)]
        stats = self._run_tasks(p, k, paths, todo) if todo else []
        for name in p.outputs:
            self.store.finalize_term_store(k, name)
        self.products += sum(s.computed for s in stats)
        return stats

    def _run_tasks(self, p: Pass, k: int, paths: dict, todo: list[int]) -> list[BlockStats]:
        """The pass's tasks for the row blocks ``todo``, on the runner."""
        t0 = time.perf_counter()
        spec = self._spec(p, k, paths)
        try:
            shared = {**self.shared, "Z": self.probes} if p.probed else self.shared
            stats = self.runner.map(spec, row_blocks(self.T.shape[0], self.tile_size, todo),
                                    shared, progress=self.settings.progress,
                                    desc=f"term {k} {p.op}")
        finally:
            self.runner.end_pass(spec.pass_id)
        self.timing.add(time.perf_counter() - t0, stats, self.runner.threads)
        return stats

    def _spec(self, p: Pass, k: int, paths: dict) -> PassSpec:
        inputs = tuple((alias, str(self.store.term_path(term, name)))
                       for alias, name, term in p.inputs)
        return PassSpec(
            op=p.op, term=k, task=p.task, T=self.T_path, first_bounce=self.fb.digest,
            zero_diagonal=self.fb.zero_diagonal, n=self.T.shape[0],
            block_rows=self.tile_size, dtype=np.dtype(self.T.dtype).name, memory=self.policy,
            inputs=inputs, scaled=p.scaled,
            outputs=tuple((name, str(path)) for name, path in paths.items()),
            right=p.right, **self.settings.thresholds.spec_fields(),
            kernel_threads=self.kernel_threads, pass_id=new_pass_id())

    def _term_attrs(self, k: int) -> StoreAttrs:
        meta = {"inverse": {**self._term_metadata(), "term": k, "complete": False}}
        return StoreAttrs(self.T.shape, self.tile_size, self.T.dtype, metadata=meta,
                          pixel_order=self.T.pixel_order)

    def _term_metadata(self) -> dict:
        """What every term store records of the series (``bigT info`` shows it)."""
        return {"method": self.series.name, **self.settings.thresholds.recorded(),
                "first_bounce": self.fb.kind, "spectral_radius": self.record.spectral_radius,
                "excluded_pixels": self.fb.excluded}

    # --- publishing a term ----------------------------------------------------------

    def _finish_term(self, k: int, stats: list[BlockStats], t0: float,
                     XZ: np.ndarray | None = None) -> None:
        """Estimate term k's residual, then publish it (redirect and record). ``XZ``
        is X_k Z for the probes when known; else X_k is read to compute it."""
        X = open_store(self.store.term_path(k, "X"))
        t_res = time.perf_counter()

        def apply_X(Z: np.ndarray) -> np.ndarray:
            nonlocal XZ
            if XZ is None:
                XZ = self._apply_X(X, Z)
            return XZ

        # the same probes at every term, so that two terms' residuals compare exactly
        res_rel, res_abs = estimate_residual(self._apply_M, apply_X, self.fb,
                                             seed=self.settings.seed)
        self._check_residual_falls(k, res_rel)
        now = time.perf_counter()
        rec = _term_record(k, stats, X, (res_rel, res_abs), now - t0, now - t_res)
        record = self.record.replace(term=k, dir=k, history=self.record.history + (rec,))
        meta = {**self._term_metadata(), "term": k, "dir": k, "residual": res_rel,
                "residual_abs": res_abs, "record": rec.to_dict()}
        self.store.publish(record.to_stored(), X, meta)
        self.record = record
        self.XZ = XZ

    def _check_residual_falls(self, k: int, residual: float) -> None:
        """Refuse term k (unless forced) when its residual grew from the held term's and
        exceeds the smallest so far ``config.RESIDUAL_GROWTH`` times: the series
        diverges, whatever the spectral radius estimate said. The held term stays
        published."""
        h = [r for r in self.record.history if r.residual is not None]
        if self.settings.force or not h:
            return
        before = h[-1].residual
        if residual > before and residual > config.RESIDUAL_GROWTH * min(r.residual for r in h):
            raise DivergenceError(
                f"the residual grew from {before:.3e} at term {h[-1].term} to {residual:.3e} "
                f"at term {k}: the series diverges (spectral radius estimate "
                f"{self.record.spectral_radius}). The inverse keeps term {h[-1].term}; "
                "{option} goes on anyway", self.store.path, option=("force", True))

    # --- mat-vecs -------------------------------------------------------------------

    def _apply_M(self, V: np.ndarray, largest: bool = False) -> np.ndarray:
        spec = matvec_spec("largest-M" if largest else "matvec-M", self.T_path,
                           self.T.shape[0], self.tile_size, self.T.dtype, memory=self.policy,
                           T=self.T_path, first_bounce=self.fb.digest,
                           zero_diagonal=self.fb.zero_diagonal, largest=largest)
        return matvec(self.runner, spec, V, self.shared)

    def _m_nonpositive(self) -> bool:
        """Whether M = I - T F^-1 has no positive entry (a transport with no negative
        entry and F = diag T): one pass over M's rows, which the spectral radius's
        products then find in the tile cache."""
        largest = self._apply_M(np.zeros((self.T.shape[0], 1)), largest=True)
        return bool(largest.max(initial=0.0) <= 0.0)

    def _apply_X(self, X, V: np.ndarray) -> np.ndarray:
        spec = matvec_spec("matvec-X", str(X.path), X.shape[0], X.tile_size, X.dtype,
                           memory=self.policy, cache_tiles=False)
        return matvec(self.runner, spec, V)

    # --- reporting ------------------------------------------------------------------

    def _warn_row_width(self, held: int, k: int) -> None:
        """Warn before a term whose output tile rows may not fit the memory plan."""
        X = StoreOperand(open_store(self.store.term_path(held, "X")))
        widest = max((X.row_bytes(j) for j in range(X.grid[0])), default=0)
        h = self.record.history
        growth = 1.0
        # X_0 = F^-1 is a diagonal: its growth to X_1 (T's width) predicts nothing
        if len(h) >= 2 and h[-2].term >= 1 and h[-2].nnz_X:
            growth = h[-1].nnz_X / h[-2].nnz_X
        tightest = min(self.plans.values(), key=lambda p: p.work_bytes_per_task)
        warn_if_rows_outgrow(tightest, widest, growth, k, self.store.path)

    def _memory_text(self) -> str:
        if len(self.plans) == 1:
            return next(iter(self.plans.values())).describe()
        return "; ".join(f"{addr}: {plan.describe()}" for addr, plan in sorted(self.plans.items()))

    def _report(self, stopped, resumed_from, t_rho, seconds, rho: SpectralRadius,
                computed: bool) -> InverseReport:
        rec, th = self.record, self.settings.thresholds
        return InverseReport(
            path=str(self.store.path), terms=rec.term, requested_terms=self.settings.terms,
            method=self.series.name, prune=th.prune, prune_feed=th.feed,
            prune_operator=th.operator, first_bounce=self.fb.kind,
            spectral_radius=rho.value, spectral_uncertainty=rho.uncertainty,
            spectral_method=rho.method, spectral_computed=computed,
            excluded_pixels=self.fb.excluded, residual=rec.residual,
            stopped=stopped, resumed_from=resumed_from, products=self.products,
            seconds=seconds, n=self.T.shape[0], nnz_T=int(self.T.nnz), history=rec.history,
            seconds_spectral_radius=t_rho, memory=self._memory_text(),
            scheduler=self.runner.describe(), threads=self.runner.threads,
            tile_size=self.tile_size,
            tasks=self.timing.tasks, task_overhead_ms=self.timing.overhead_ms(),
            peak_memory=tuple(sorted(self.runner.peak_memory().items())))


def _term_record(k: int, stats: list[BlockStats], X, residual: tuple[float, float],
                 seconds: float, residual_seconds: float) -> TermRecord:
    """Term k's record from its tasks' stats, its X and its residual estimate
    (relative, absolute)."""
    return TermRecord(
        term=k, seconds=seconds,
        nnz_P=int(sum(s.nnz_P for s in stats)), nnz_X=int(X.nnz),
        tiles_computed=int(sum(s.computed for s in stats)),
        tiles_skipped=int(sum(s.skipped for s in stats)),
        rows_skipped=int(sum(1 for s in stats if s.row_skipped)),
        residual=residual[0], residual_abs=residual[1],
        multiply_adds=int(sum(s.multiply_adds for s in stats)),
        kernel_seconds=float(sum(s.kernel_seconds for s in stats)),
        residual_seconds=residual_seconds)
