"""The :class:`~.report.InverseReport` of one engine run, from how the run ended
(:class:`RunOutcome`) and what its pieces hold: the layout, the store's record, the
passes' totals and the runner's description and peak memory."""

from __future__ import annotations

from dataclasses import dataclass

from ..spectral import SpectralRadius
from .engine_path import PathChoice
from .passes import PassTotals
from .records import SeriesRecord
from .report import InverseReport
from .run_setup import RunLayout
from .settings import SeriesSettings


@dataclass(frozen=True)
class RunOutcome:
    """How one run ended.

    Attributes
    ----------
    stopped : str
        Why it stopped (the report's ``stopped``).
    resumed_from : int or None
        The term the store held when the run began.
    rho : SpectralRadius
    rho_computed : bool
        This run estimated rho (else it was read from the store's record).
    seconds_spectral_radius, seconds : float
        The time rho took, and the whole run's.
    """

    stopped: str
    resumed_from: int | None
    rho: SpectralRadius
    rho_computed: bool
    seconds_spectral_radius: float
    seconds: float


def inverse_report(outcome: RunOutcome, layout: RunLayout, record: SeriesRecord,
                   settings: SeriesSettings, method: str, totals: PassTotals, runner,
                   store_path, path: PathChoice) -> InverseReport:
    """The report of the run that ended as ``outcome``, ``record`` the store's last;
    ``path`` the path the run took last (and why)."""
    th, rho = settings.thresholds, outcome.rho
    return InverseReport(
        path=str(store_path), terms=record.term, requested_terms=settings.terms,
        method=method, prune=th.prune, prune_feed=th.feed, prune_operator=th.operator,
        first_bounce=layout.fb.kind, spectral_radius=rho.value,
        spectral_uncertainty=rho.uncertainty, spectral_method=rho.method,
        spectral_computed=outcome.rho_computed, excluded_pixels=layout.fb.excluded,
        residual=record.residual, stopped=outcome.stopped,
        resumed_from=outcome.resumed_from, products=totals.products,
        seconds=outcome.seconds, n=layout.n, nnz_T=int(layout.T.nnz),
        history=record.history, seconds_spectral_radius=outcome.seconds_spectral_radius,
        memory=layout.memory_text(), scheduler=runner.describe(), threads=runner.threads,
        tile_size=layout.tile_size, tasks=totals.tasks, task_overhead_ms=totals.overhead_ms(),
        peak_memory=tuple(sorted(runner.peak_memory().items())),
        engine_path=path.name, engine_path_reason=path.reason,
        task_costs=runner.costs.total())
