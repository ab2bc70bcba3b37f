"""Publishing a finished term in the inverse store, and letting go of the one before.

A term is published only once complete: its stores are written under ``tKKKK`` by the
tasks of its passes (in memory, by :class:`~.resident.ResidentPasses`, possibly after
later terms were computed) and its residual estimated; then :meth:`InverseStore.publish`
records the term in X's metadata, flips the root's redirect to it and writes the root
record, in that order. Only then is the previous term deleted (in the background). A
crash leaves the previous term readable; the order of these writes is what the crash
harness (tests/reliability) checks.
"""

from __future__ import annotations

import time

from ..schedule.spec import BlockStats
from ..storage import InverseStore
from ..storage.inverse_store import term_dir
from .first_bounce import FirstBounce
from .records import SeriesRecord, TermRecord
from .settings import Thresholds
from .probes import TermResidual


def series_metadata(method: str, thresholds: Thresholds, fb: FirstBounce,
                    spectral_radius: float | None) -> dict:
    """What every term store records of the series (``bigT info`` shows it)."""
    return {"method": method, **thresholds.recorded(), "first_bounce": fb.kind,
            "spectral_radius": spectral_radius, "excluded_pixels": fb.excluded}


def term_record(k: int, stats: list[BlockStats], X, residual: TermResidual,
                t0: float, engine_path: str = "out-of-core", tasks=()) -> TermRecord:
    """Term k's record from its tasks' stats, its X and its residual estimate; ``t0``
    is ``time.perf_counter()`` when the term began; ``engine_path`` the path that
    computed it (:mod:`.engine_path`); ``tasks`` what its tasks cost, by kind
    (:meth:`bigT.schedule.costs.CostLedger.since`)."""
    now = time.perf_counter()
    return TermRecord(
        term=k, seconds=now - t0,
        nnz_P=int(sum(s.nnz_P for s in stats)), nnz_X=int(X.nnz),
        tiles_computed=int(sum(s.computed for s in stats)),
        tiles_skipped=int(sum(s.skipped for s in stats)),
        rows_skipped=int(sum(1 for s in stats if s.row_skipped)),
        residual=residual.relative, residual_abs=residual.absolute,
        multiply_adds=int(sum(s.multiply_adds for s in stats)),
        kernel_seconds=float(sum(s.kernel_seconds for s in stats)),
        residual_seconds=now - residual.started, engine_path=engine_path,
        tasks=tuple(tasks))


def with_term(record: SeriesRecord, term: TermRecord) -> SeriesRecord:
    """``record`` holding ``term`` after its terms, not yet published (its ``dir``, the
    term readers see, unchanged)."""
    return record.replace(term=term.term, history=record.history + (term,))


def publish_held(store: InverseStore, record: SeriesRecord, X, metadata: dict) -> SeriesRecord:
    """Publish the term ``record`` holds (the last of its history; its X the store
    ``X``): X's metadata (the series' ``metadata`` and the term's), the redirect, the
    root record. Returns the record now stored."""
    published = record.replace(dir=record.history[-1].term)
    store.publish(published.to_stored(), X, term_metadata(record, metadata))
    return published


def term_metadata(record: SeriesRecord, metadata: dict) -> dict:
    """What X of the term ``record`` holds (the last of its history) records of it
    once published: the series' ``metadata`` and the term's (its ``inverse``
    metadata)."""
    term = record.history[-1]
    k = term.term
    return {**metadata, "term": k, "dir": k, "residual": term.residual,
            "residual_abs": term.residual_abs, "record": term.to_dict()}


def let_go_of_term(store: InverseStore, runner, held: int) -> None:
    """Delete term ``held``, once a later one is published: the processes' caches let
    go of it first (their open stores hold its lease), then it is deleted in the
    background while the next term computes (the run waits for it before it
    returns: :meth:`InverseStore.settle`)."""
    runner.end_pass(None, forget=(str(store.path / term_dir(held)),))
    store.drop_term(held, background=True)
