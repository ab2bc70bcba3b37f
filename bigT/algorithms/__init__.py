"""bigT.algorithms: the stratified inverse (paper eq. 13) and first-bounce recovery
(eq. 33). See :mod:`bigT.algorithms.stratified` for the conventions.

Each name is imported from its module on first use, so that a light module of this
layer (:mod:`.defaults`, which ``bigT invert --help`` reads) is imported without the
engine (numpy, scipy, the stores: ~0.5 s).
"""

from __future__ import annotations

import importlib
import importlib.util

#: Public name -> the module defining it, imported on first use.
_LAZY = {
    **dict.fromkeys(("SpectralRadius", "spectral_radius"), "bigT.spectral"),
    **dict.fromkeys(("FirstBounce", "recover_first_bounce", "resolve_first_bounce"),
                    "bigT.algorithms.first_bounce"),
    "SeriesMethod": "bigT.algorithms.methods",
    **dict.fromkeys(("SeriesRecord", "TermRecord"), "bigT.algorithms.records"),
    "InverseReport": "bigT.algorithms.report",
    "estimate_residual": "bigT.algorithms.residual",
    **dict.fromkeys(("METHODS", "stratified_inverse"), "bigT.algorithms.stratified"),
    **dict.fromkeys(("TargetReport", "invert_to_target"), "bigT.algorithms.target"),
}

__all__ = [
    "METHODS", "FirstBounce", "InverseReport", "SeriesMethod", "SeriesRecord",
    "SpectralRadius", "TermRecord", "estimate_residual", "recover_first_bounce",
    "resolve_first_bounce", "spectral_radius", "stratified_inverse", "TargetReport",
    "invert_to_target",
]


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    # a submodule, as ``bigT.algorithms.stratified`` was reachable when this package
    # imported them all
    if importlib.util.find_spec(f"{__name__}.{name}") is not None:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module 'bigT.algorithms' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_LAZY))
