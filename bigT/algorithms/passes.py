"""One pass of a term over its row blocks: the pass's output stores created (or
resumed), a task per row block not yet complete in all of them handed to the runner,
the stores finalized from their row markers; and the totals of the passes run (tasks,
time, tiles computed) for the report.

What a pass computes is the series method's (:class:`~.methods.Pass`); this module
only lays it out as a :class:`~bigT.schedule.spec.PassSpec` and runs it.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass

import numpy as np

from ..schedule.memory import warn_if_rows_outgrow
from ..schedule.operators import StoreOperand
from ..schedule.runner import new_pass_id, worker_path
from ..schedule.spec import BlockStats, PassSpec, row_blocks
from ..storage import InverseStore, StoreAttrs, completed_rows
from ..storage import open as open_store
from .methods import Pass, SeriesMethod
from .records import TermRecord
from .run_setup import RunLayout
from .settings import SeriesSettings


@dataclass(frozen=True)
class PassTotals:
    """The product passes' tasks, the tiles they computed, and the threads' time not
    spent inside the tasks: (wall time x threads - time in tasks) / tasks is what
    scheduling a task costs (submission, scattering, results, idle threads at the end
    of a pass)."""

    tasks: int = 0
    products: int = 0
    thread_seconds: float = 0.0
    task_seconds: float = 0.0

    def plus(self, wall: float, stats: list[BlockStats], threads: int) -> PassTotals:
        """These totals and one pass's: its wall time on ``threads`` threads and its
        tasks' stats."""
        return dataclasses.replace(
            self, tasks=self.tasks + len(stats),
            products=self.products + sum(s.computed for s in stats),
            thread_seconds=self.thread_seconds + wall * threads,
            task_seconds=self.task_seconds + sum(s.seconds for s in stats))

    def overhead_ms(self) -> float:
        """Scheduling cost per task, milliseconds (0 before any task)."""
        if not self.tasks:
            return 0.0
        return 1e3 * max(0.0, self.thread_seconds - self.task_seconds) / self.tasks


def exhausted_before(series: SeriesMethod, p: Pass, held: int,
                     store: InverseStore) -> str | None:
    """The method's reason why every term after ``held`` is zero (the series is
    exhausted), read from the stores pass ``p`` would read; None when it is not."""
    for _alias, name, term in p.inputs:
        reason = series.exhausted(held, name, open_store(store.term_path(term, name)))
        if reason:
            return reason
    return None


class PassRunner:
    """Runs the series' passes for the run laid out by ``layout``; ``probes`` (the
    residual probes Z, shape (n, p)) go to the passes that report (X_k - X_{k-1}) Z.
    ``totals`` sums the passes run."""

    def __init__(self, layout: RunLayout, store: InverseStore, runner,
                 settings: SeriesSettings, probes: np.ndarray):
        self.layout, self.store, self.runner, self.settings = layout, store, runner, settings
        self.probes = probes
        self.totals = PassTotals()
        #: the stores the passes finalized, opened, by (term, name): the engine's
        #: publication reads X from here rather than opening it again
        self.finalized: dict[tuple[int, str], object] = {}

    def run(self, p: Pass, k: int, metadata: dict, write: bool = True) -> list[BlockStats]:
        """Run pass ``p`` of term ``k``: create (or resume) its output stores, recording
        ``metadata`` (the series', :func:`.publish.series_metadata`), run a task per
        row block not yet complete in all of them, finalize them from their row
        markers. Returns the stats of the tasks run (none when resumed complete).
        ``write`` is the in-memory path's (:class:`~.resident.ResidentPasses`): the
        tasks write every term."""
        n_blocks = self.layout.n_blocks
        paths = {name: self.store.prepare_term_store(k, name,
                                                     term_store_attrs(self.layout, k, metadata))
                 for name in p.outputs}
        done = [set(completed_rows(path, n_blocks)) for path in paths.values()]
        todo = [i for i in range(n_blocks) if any(i not in d for d in done)]
        stats = self._run_tasks(p, k, paths, todo) if todo else []
        for name in p.outputs:
            self.finalized[(k, name)] = self.store.finalize_term_store(k, name)
        return stats

    def close(self) -> None:
        """Nothing held between passes (the runner's caches are let go by the caller)."""

    def forget_unwritten(self, before: int) -> None:
        """Nothing unwritten: every term's tasks write it."""

    def exhausted_before(self, series: SeriesMethod, p: Pass, held: int) -> str | None:
        """:func:`exhausted_before` on this run's store."""
        return exhausted_before(series, p, held, self.store)

    def warn_row_width(self, held: int, k: int, history: tuple[TermRecord, ...]) -> None:
        """Warn before term ``k`` when its output tile rows may not fit the tightest
        memory plan: the held term's widest row, grown as X grew at the last term."""
        X = StoreOperand(open_store(self.store.term_path(held, "X")))
        widest = max((X.row_bytes(j) for j in range(X.grid[0])), default=0)
        growth = 1.0
        # X_0 = F^-1 is a diagonal: its growth to X_1 (T's width) predicts nothing
        if len(history) >= 2 and history[-2].term >= 1 and history[-2].nnz_X:
            growth = history[-1].nnz_X / history[-2].nnz_X
        tightest = min(self.layout.plans.values(), key=lambda p: p.work_bytes_per_task)
        warn_if_rows_outgrow(tightest, widest, growth, k, self.store.path)

    def _run_tasks(self, p: Pass, k: int, paths: dict, todo: list[int]) -> list[BlockStats]:
        """The pass's tasks for the row blocks ``todo``, on the runner."""
        lay = self.layout
        t0 = time.perf_counter()
        spec = self._spec(p, k, paths)
        try:
            shared = {**lay.shared, "Z": self.probes} if p.probed else lay.shared
            stats = self.runner.map(spec, row_blocks(lay.n, lay.tile_size, todo), shared,
                                    progress=self.settings.progress, desc=f"term {k} {p.op}")
        finally:
            self.runner.end_pass(spec.pass_id)
        self.totals = self.totals.plus(time.perf_counter() - t0, stats, self.runner.threads)
        return stats

    def _spec(self, p: Pass, k: int, paths: dict) -> PassSpec:
        lay = self.layout
        # worker_path: a store in object storage travels as its ObjectPath, with the
        # storage options its location was given, not as a bare URL
        inputs = tuple((alias, worker_path(self.store.term_path(term, name)))
                       for alias, name, term in p.inputs)
        return PassSpec(
            op=p.op, term=k, task=p.task, T=lay.T_path, first_bounce=lay.fb.digest,
            zero_diagonal=lay.fb.zero_diagonal, n=lay.n, block_rows=lay.tile_size,
            dtype=np.dtype(lay.T.dtype).name, memory=lay.policy, inputs=inputs,
            scaled=p.scaled, outputs=tuple((name, worker_path(path)) for name, path in paths.items()),
            right=p.right, **self.settings.thresholds.spec_fields(),
            kernel_threads=lay.kernel_threads, pass_id=new_pass_id())


def term_store_attrs(layout: RunLayout, k: int, metadata: dict) -> StoreAttrs:
    """A new store of term k (X, P or R, on either path): T's shape, dtype and pixel
    order, the run's tile size, the series' metadata marked incomplete."""
    meta = {"inverse": {**metadata, "term": k, "complete": False}}
    return StoreAttrs(layout.T.shape, layout.tile_size, layout.T.dtype, metadata=meta,
                      pixel_order=layout.T.pixel_order)
