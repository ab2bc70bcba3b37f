"""bigT.algorithms: the stratified inverse (paper eq. 13) and first-bounce recovery
(eq. 33). See :mod:`bigT.algorithms.stratified` for the conventions."""

from ..spectral import SpectralRadius, spectral_radius
from .first_bounce import FirstBounce, recover_first_bounce, resolve_first_bounce
from .methods import SeriesMethod
from .records import SeriesRecord, TermRecord
from .report import InverseReport
from .residual import estimate_residual
from .stratified import METHODS, stratified_inverse
from .target import TargetReport, invert_to_target

__all__ = [
    "METHODS", "FirstBounce", "InverseReport", "SeriesMethod", "SeriesRecord",
    "SpectralRadius", "TermRecord", "estimate_residual", "recover_first_bounce",
    "resolve_first_bounce", "spectral_radius", "stratified_inverse", "TargetReport",
    "invert_to_target",
]
