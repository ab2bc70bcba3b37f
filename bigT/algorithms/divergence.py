"""The engine's two refusals of a diverging series; ``force`` skips both.

Before term 0, rho(M) is estimated once per store (:func:`bigT.spectral.spectral_radius`:
a Collatz-Wielandt bracket where M = -|M|, as for any grey transport without negative
entries; where M has both signs, as with colour, the rigorous upper bound rho(|M|) when
it is well under 1; else Arnoldi) and kept in the store's record; the run is refused unless
rho + its uncertainty < 1. After every term, a residual that grew and exceeds the
smallest so far ``config.RESIDUAL_GROWTH`` times is refused before the term is
published (not any growth: with a non-normal M, or at the pruning floor, a convergent
series may grow for a term).
"""

from __future__ import annotations

from typing import Callable

from .. import config
from ..errors import DivergenceError
from ..spectral import SpectralRadius, spectral_radius
from .first_bounce import FirstBounce
from .matvecs import MatVecs
from .records import SeriesRecord


def checked_radius(record: SeriesRecord, matvecs: MatVecs, seed: int, force: bool,
                   save: Callable[[SeriesRecord], None]) -> tuple[SpectralRadius, bool]:
    """(rho(M), whether it was estimated now): read from ``record``, else estimated and,
    once converged, recorded through ``save`` (else estimated anew on the next run);
    then a series that may diverge is refused (:func:`refuse_diverging`)."""
    rho = recorded_radius(record)
    computed = rho is None
    if computed:
        rho = estimate_radius(matvecs, seed)
        if rho.converged:
            save(with_radius(record, rho))
    refuse_diverging(rho, matvecs.layout.fb, matvecs.layout.T.path, force)
    return rho, computed


def recorded_radius(record: SeriesRecord) -> SpectralRadius | None:
    """The estimate of rho(M) the store's record holds; None when it must be estimated
    (none recorded, or one without an uncertainty: the older power iteration's, which
    reads low on crowded spectra)."""
    if record.spectral_radius is None or record.spectral_uncertainty is None:
        return None
    return SpectralRadius(record.spectral_radius, record.spectral_uncertainty,
                          record.spectral_products or 0, record.spectral_method or "recorded")


def estimate_radius(matvecs: MatVecs, seed: int) -> SpectralRadius:
    """rho(M) from products with M on the runner: the bracket when M has no positive
    entry; else (colour, or a first bounce other than diag T) the upper bound
    rho(|M|) from products with |M| when it is well under 1, ARPACK otherwise (the
    engine needs only the bound: the refusal asks rho < 1, and the report says which
    kind of number it holds)."""
    lay = matvecs.layout
    nonpositive = matvecs.m_nonpositive()
    return spectral_radius(matvecs.apply_M, lay.n, lay.fb.active, seed=seed,
                           nonpositive=nonpositive,
                           apply_abs=None if nonpositive else matvecs.apply_abs_M)


def with_radius(record: SeriesRecord, rho: SpectralRadius) -> SeriesRecord:
    """``record`` holding the estimate ``rho``."""
    return record.replace(spectral_radius=rho.value, spectral_uncertainty=rho.uncertainty,
                          spectral_products=rho.products, spectral_method=rho.method)


def refuse_diverging(rho: SpectralRadius, fb: FirstBounce, T_path, force: bool) -> None:
    """DivergenceError (naming T) unless rho + its uncertainty < 1, or ``force``."""
    if rho.upper < 1 or force:
        return
    raise DivergenceError(
        f"the spectral radius of M = I - T F^-1 is {rho.describe()}, so it may be "
        f">= 1 (first bounce {fb.kind}): the series diverges. Try the "
        "diagonal first bounce, a higher threshold on T's small entries (or "
        "denoising it), fixing negative or zero diagonal entries, or {option} "
        "to run anyway", T_path, option=("force", True))


def refuse_growing_residual(record: SeriesRecord, k: int, residual: float, force: bool,
                            store_path) -> None:
    """DivergenceError (naming the store) when term k's relative ``residual`` grew from
    the held term's and exceeds the smallest so far ``config.RESIDUAL_GROWTH`` times:
    the series diverges, whatever the spectral radius estimate said. The held term
    stays published. Nothing is refused with ``force``, or before a residual is held."""
    h = [r for r in record.history if r.residual is not None]
    if force or not h:
        return
    before = h[-1].residual
    if residual > before and residual > config.RESIDUAL_GROWTH * min(r.residual for r in h):
        raise DivergenceError(
            f"the residual grew from {before:.3e} at term {h[-1].term} to {residual:.3e} "
            f"at term {k}: the series diverges (spectral radius estimate "
            f"{record.spectral_radius}). The inverse keeps term {h[-1].term}; "
            "{option} goes on anyway", store_path, option=("force", True))
