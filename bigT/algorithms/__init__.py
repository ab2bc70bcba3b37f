"""bigT.algorithms: the stratified inverse (paper eq. 13) and first-bounce recovery
(eq. 33). See :mod:`bigT.algorithms.stratified` for the conventions."""

from ..storage import TermRecord
from .first_bounce import FirstBounce, recover_first_bounce, resolve_first_bounce
from .methods import SeriesMethod
from .stratified import (
    METHODS,
    InverseReport,
    estimate_residual,
    estimate_spectral_radius,
    stratified_inverse,
)

__all__ = [
    "METHODS", "FirstBounce", "InverseReport", "SeriesMethod", "TermRecord", "estimate_residual",
    "estimate_spectral_radius", "recover_first_bounce", "resolve_first_bounce",
    "stratified_inverse",
]
