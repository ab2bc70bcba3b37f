"""The engine of :func:`~bigT.algorithms.stratified_inverse`: one run's loop over terms.
:class:`InverseEngine` is the driver; each of its steps is one module's:

* :mod:`.run_setup`: the store opened or resumed under the run's fingerprint, F, the
  memory plans, the term stores' tile size (:class:`~.run_setup.RunLayout`);
* :mod:`.divergence`: rho(M) estimated (or read from the record) and a diverging
  series refused before term 0; a term whose residual grew refused after it;
* :mod:`.engine_path`: in memory or out of core, chosen once (``in_memory``), and
  left for out of core before a term whose predicted size does not fit in memory;
* :mod:`.passes`: each pass of a term run over its row blocks on the runner
  (local threads, or a dask cluster's workers), and the totals of the passes; or, in
  memory, :mod:`.resident`: the same passes on whole matrices, written into the same
  term stores;
* :mod:`.matvecs` and :mod:`.probes`: the products with M and X (in memory:
  :class:`.resident.ResidentMatVecs`), and each term's residual estimate, the probes'
  X Z carried from term to term;
* :mod:`.publish`: a finished term published (X's record, redirect, root record) and
  the previous term deleted in the background. In memory, a term is written and
  published only where it matters (:meth:`InverseEngine._writes`): the run's last
  term, each term a caller's ``on_term`` reads (every term, unless it has a
  ``reads_term`` saying which), a term computed
  :data:`PUBLISH_INTERVAL_SECONDS` after the last one published (what a crash may cost
  again), and the term held before the run leaves memory or stops; the others stay in
  memory, their records in the history all the same;
* :mod:`.outcome`: the :class:`~.report.InverseReport` from how the run ended.

The driver holds what changes during the run: the record (the term held, published or,
in memory, not yet) and the probes' X Z for it. A term is published only once complete;
a crash leaves the last term published readable, and the same call resumes at the
first incomplete row block of the next term. ``force`` skips both refusals of
divergence.
"""

from __future__ import annotations

import time

import numpy as np

from ..errors import DivergenceError
from ..storage import InverseStore
from ..storage import open as open_store
from ..schedule.memory import return_freed_memory
from .divergence import checked_radius, refuse_growing_residual
from .engine_path import IN_MEMORY, OUT_OF_CORE, PathChoice
from .matvecs import MatVecs
from .methods import TERM_ZERO, SeriesMethod
from .passes import PassRunner
from .resident import ResidentMatrices, ResidentMatVecs, ResidentPasses
from .publish import (let_go_of_term, publish_held, series_metadata, term_metadata, term_record,
                      with_term)
from .records import SeriesRecord
from .report import InverseReport
from .outcome import RunOutcome, inverse_report
from .run_setup import open_run
from .settings import SeriesSettings
from .probes import ProbedResidual, TermResidual

#: In memory, a term the run goes past is still published when this many seconds have
#: passed since the last term published: what a crash may cost again (at most this and
#: one term), so that a long run's progress is durable. The others are not written
#: (their records are kept): at n = 1000..5120 writing and publishing a term durably
#: (2 stores, ~75 fsyncs) costs more than its product, and on the dense 384x512 corner
#: (~10 s for 4 terms) an intermediate term's write took 1.1 s, 10 % of the run, at the
#: 5 s this was (issue #30). At 30 s, a run that short publishes only its last term, and
#: a long one spends at most ~4 % of its time on intermediate writes of that size. 0:
#: every term written and published as it is computed.
PUBLISH_INTERVAL_SECONDS = 30.0

#: In memory, the heap's freed pages are handed back before a term
#: (:func:`~bigT.schedule.memory.return_freed_memory`) only when the matrices held
#: take at least this many bytes: below it the pages are few, and at n = 1000 the
#: seven calls cost more than the terms' products' bookkeeping (issue #30).
TRIM_MIN_BYTES = 64 << 20


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
    in_memory : bool or None
        :func:`.engine_path.choose_path`'s (None: chosen from the memory budget).
    T_rows : TileRows or None
        T's tile rows a caller holds (:func:`.run_setup.open_run`: F and, in memory,
        M taken from them instead of reading T again).

    It holds what changes during the run, ``record`` (the store's
    :class:`~.records.SeriesRecord`: the term held), ``XZ`` (X Z of that term for
    the residual probes) and ``path`` (in memory or out of core, and why), and the
    pieces that run its steps: ``layout`` (fixed at set-up), ``matvecs``,
    ``residual`` and ``passes`` (in memory, :mod:`.resident`'s).
    """

    def __init__(self, T, store: InverseStore, series: SeriesMethod, runner,
                 settings: SeriesSettings, first_bounce, memory_limit, in_memory=False,
                 T_rows=None):
        self.store, self.series, self.runner, self.settings = store, series, runner, settings
        self.layout, self.record = open_run(T, store, series, runner, settings,
                                            first_bounce, memory_limit, in_memory, T_rows)
        self.path: PathChoice = self.layout.path
        if self.path.in_memory:
            matrices = ResidentMatrices(self.layout, store, runner.threads)
            self.matvecs = ResidentMatVecs(matrices, runner.threads)
        else:
            self.matvecs = MatVecs(runner, self.layout)
        self.residual = ProbedResidual.for_run(self.matvecs, settings.seed)
        if self.path.in_memory:
            # without residual estimates no pass multiplies its new entries by the probes
            probes = self.residual.Z if self._estimates_residual() else None
            self.passes = ResidentPasses(matrices, store, settings, probes,
                                         runner.threads, self.path.budget, series)
        else:
            self.passes = PassRunner(self.layout, store, runner, settings, self.residual.Z)
        self.XZ: np.ndarray | None = None  # X Z for the term held (None: X is read)
        self._published_at = time.perf_counter()  # the last publication (or the start)
        self._held_unpublished = False  # in memory: the term held not written yet
        # whether a term was written or published since the store's last clean: in
        # memory a term the run goes past writes nothing, so nothing needs cleaning
        # before the next one (the run's end cleans whatever readers let go meanwhile)
        self._wrote_since_clean = True

    def run(self, t_start: float) -> InverseReport:
        """Estimate rho (refusing a diverging series), compute the terms, report."""
        resumed_from = self.record.term
        try:
            t0 = time.perf_counter()
            rho, computed = checked_radius(self.record, self.matvecs, self.settings.seed,
                                           self.settings.force, self._save)
            t_rho = time.perf_counter() - t0
            if self.record.term is None:
                self._term_zero()
        except BaseException:
            # refused (a diverging series) or stopped before any term was finished: an
            # output this run created holds nothing worth keeping
            self.passes.close()
            if self.layout.created and self.record.term is None:
                self.store.discard()
            raise
        try:
            stopped = self._extend(resumed_from)
            self._publish_held()  # the term the run ends with, when kept in memory
        finally:
            self.passes.close()
            self.store.settle()
        if self.record.dir is not None:
            self.store.clean(keep={self.record.dir})  # terms readers held when dropped
        outcome = RunOutcome(stopped, resumed_from, rho, computed, t_rho,
                             time.perf_counter() - t_start)
        return inverse_report(outcome, self.layout, self.record, self.settings,
                              self.series.name, self.passes.totals, self.runner,
                              self.store.path, self.path)

    def _extend(self, resumed_from: int | None) -> str:
        """Compute terms until ``terms`` is held, ``tol`` is reached or the series is
        exhausted; returns why it stopped."""
        terms, on_term = self.settings.terms, self.settings.on_term
        if self.record.exhausted_at is not None and self.record.term < terms:
            self._save(self.record.replace(term=terms))
            return f"series exhausted at term {self.record.exhausted_at}"
        computed = False
        if resumed_from is not None and on_term and self.record.term < terms:
            # the term held may already be enough: the callback sees it before any work
            reason = self._call_on_term()
            if reason:
                return reason
        while self.record.term < terms:
            if self._tol_reached():
                return f"tol {self.settings.tol:g} reached"
            computed = True
            reason = self._next_term() or (self._call_on_term() if on_term else None)
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
        self._wrote_since_clean = False
        t0 = time.perf_counter()
        write = self._writes(0)
        stats = self.passes.run(TERM_ZERO, 0, self._series_metadata(), write=write)
        self._finish_term(0, stats, t0, XZ=self.residual.term_zero_XZ(), publish=write)

    def _next_term(self) -> str | None:
        """Compute the term after the one held and publish it (in memory, unless
        :meth:`_writes` says otherwise); a reason when the series turns out exhausted
        instead."""
        held = self.record.term
        k = self.series.next_term(held)
        self._leave_memory_unless_fits(held)
        if time.perf_counter() - self._published_at >= PUBLISH_INTERVAL_SECONDS:
            self._publish_held()
        self.passes.warn_row_width(held, k, self.record.history)
        if self._wrote_since_clean or not self.path.in_memory:
            self.store.clean(keep={self.record.dir, k})
            self._wrote_since_clean = False
        if not self.path.in_memory or self.passes.matrices.bytes_held() >= TRIM_MIN_BYTES:
            return_freed_memory()  # the last term's temporaries: each term starts from what it holds
        t0 = time.perf_counter()
        stats = []
        write = self._writes(k)
        for p in self.series.passes(held, k):
            reason = self.passes.exhausted_before(self.series, p, held)
            if reason:
                self._publish_held()
                self._save(self.record.replace(term=self.settings.terms, exhausted_at=held))
                return reason
            stats += self.passes.run(p, k, self._series_metadata(), write=write)
        self._finish_term(k, stats, t0, XZ=self.residual.updated_XZ(self.XZ, stats),
                          publish=write)
        return None

    def _writes(self, k: int) -> bool:
        """Whether term ``k`` is written and published as soon as it is computed: out
        of core always (its tasks write it); in memory when it is the run's last term
        by ``terms``, a caller's ``on_term`` reads it (:meth:`_on_term_reads`), or
        :data:`PUBLISH_INTERVAL_SECONDS` is 0 (else it is published later only when
        that interval has passed, or the run stops at it: :meth:`_publish_held`)."""
        return (not self.path.in_memory or self._on_term_reads(k)
                or k >= self.settings.terms or PUBLISH_INTERVAL_SECONDS <= 0)

    def _estimates_residual(self) -> bool:
        """Whether each term's residual is estimated (:mod:`.probes`): unless the
        caller's ``on_term`` measures the terms' errors itself and says so by a false
        ``needs_residual`` (the target-error search: its probes' errors decide, so the
        estimate, an M product per term, ~0.2 s each on the dense 384x512 corner, and
        its refusal of a growing residual are left out; the terms' records then hold
        no residual), nor ``tol`` asks for it."""
        on_term = self.settings.on_term
        return (self.settings.tol is not None or on_term is None
                or bool(getattr(on_term, "needs_residual", True)))

    def _call_on_term(self) -> str | None:
        """The caller's ``on_term`` on the term held; one with a true ``takes_X`` also
        gets ``X=``, the term's X as this process holds it in memory (csr_array,
        shape (n, n), the stored order; None out of core or where it is not held), to
        multiply with instead of reading the store (the target-error search: on the
        dense 384x512 corner, X's 3.4e7 entries read back cost 0.5-1 s a term
        measured)."""
        on_term = self.settings.on_term
        if not getattr(on_term, "takes_X", False):
            return on_term(self.record)
        held = None
        if self.path.in_memory:
            held = self.passes.matrices.held.get(("X", self.record.term))
        return on_term(self.record, X=held)

    def _on_term_reads(self, k: int) -> bool:
        """Whether the caller's ``on_term`` reads term ``k`` from the store: every term,
        unless the callable says otherwise by its ``reads_term(k)`` (the target-error
        search reads only the terms it measures)."""
        on_term = self.settings.on_term
        if on_term is None:
            return False
        reads_term = getattr(on_term, "reads_term", None)
        return True if reads_term is None else bool(reads_term(k))

    def _publish_held(self) -> None:
        """Write and publish the term held when it was kept in memory only (nothing
        to do when it is published); the term published before is let go."""
        if not self._held_unpublished:
            return
        metadata = self._series_metadata()
        # X's metadata as publishing records it, written with X (one write less)
        X = self.passes.write_term(self.record.term, metadata,
                                   inverse=term_metadata(self.record, metadata))
        self._publish(X)

    def _leave_memory_unless_fits(self, held: int) -> None:
        """In memory, go on out of core from the term ``held`` (published: the
        out-of-core passes read it from the store) when the next term's predicted size
        (the held term's, grown as X grew at the last term) does not fit the budget."""
        if not self.path.in_memory:
            return
        history = self.record.history
        last = history[-1] if history else None
        growth = 1.0
        if len(history) >= 2 and history[-2].term >= 1 and history[-2].nnz_X:
            growth = history[-1].nnz_X / history[-2].nnz_X
        if last is None or self.passes.fits(held, last.nnz_X, last.nnz_P, growth):
            return
        self._publish_held()  # the out-of-core passes read it from the store
        totals = self.passes.totals
        self.passes.close()
        self.path = PathChoice(False, f"{self.path.reason}; out of core from term "
                                      f"{held + 1}: its predicted size exceeds the budget")
        self.matvecs = MatVecs(self.runner, self.layout)
        self.residual = ProbedResidual(self.matvecs, self.residual.Z, self.residual.seed)
        self.passes = PassRunner(self.layout, self.store, self.runner, self.settings,
                                 self.residual.Z)
        self.passes.totals = totals

    def _finish_term(self, k: int, stats, t0: float, XZ: np.ndarray | None = None,
                     publish: bool = True) -> None:
        """Estimate term k's residual (``XZ``: X_k Z when known), refuse the term when
        the residual grew (the term held then published, when it was not), else hold
        it: published with ``publish``, else (in memory) its record kept and its
        matrices left unwritten. Every term computed, term 0 included, passes here
        (benchmarks/bench_tradeoff.py wraps it to measure each term)."""
        # with X Z known the estimate does not read X: in memory it runs while the
        # term's stores are still being written (``finalized`` waits for them)
        estimates = self._estimates_residual()
        residual = (TermResidual.skipped() if not estimates
                    else None if XZ is None else self.residual.estimate(None, XZ))
        X = self.passes.finalized.pop((k, "X"), None)
        if X is None:
            X = (open_store(self.store.term_path(k, "X")) if publish
                 else self.passes.matrices.term("X", k))
        self.passes.finalized.clear()  # the other stores of the term are not read again
        if residual is None:
            residual = self.residual.estimate(X, XZ)
        try:
            if estimates:
                refuse_growing_residual(self.record, k, residual.relative,
                                        self.settings.force, self.store.path)
        except DivergenceError:
            self._publish_held()  # the term the message says the inverse keeps
            raise
        term = term_record(k, stats, X, residual, t0,
                           IN_MEMORY if self.path.in_memory else OUT_OF_CORE,
                           self.runner.costs.since(t0))
        self.record = with_term(self.record, term)
        self.XZ = residual.XZ
        if publish:
            self._publish(X)
        else:
            self._held_unpublished = True
            self.passes.forget_unwritten(before=k)

    def _publish(self, X) -> None:
        """Publish the term held, whose X is the store ``X``, and let go of the term
        published before it."""
        before = self.record.dir
        self.record = publish_held(self.store, self.record, X, self._series_metadata())
        self._published_at = time.perf_counter()
        self._held_unpublished = False
        self._wrote_since_clean = True
        self.passes.forget_unwritten(before=self.record.term + 1)
        if before is not None and before != self.record.term:
            let_go_of_term(self.store, self.runner, before)

    def _save(self, record: SeriesRecord) -> None:
        self.store.save(record.to_stored())
        self.record = record

    def _series_metadata(self) -> dict:
        return series_metadata(self.series.name, self.settings.thresholds, self.layout.fb,
                               self.record.spectral_radius)
