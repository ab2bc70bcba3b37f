"""Each term's residual estimate (:func:`.residual.estimate_residual`) in the engine, with
the probes' X_k Z carried from term to term: term 0's is F^-1 Z, and a term whose tasks
all reported their rows of (X_k - X_{k-1}) Z (the power form's do) adds them to the
held term's, so that X_k is not read back; otherwise X_k Z is one product with the
stored X_k. The same probes Z serve every term, so that two terms' residuals compare
exactly.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..schedule.spec import BlockStats
from .matvecs import MatVecs
from .residual import residual_of_probes, residual_probes


@dataclass(frozen=True, eq=False)
class TermResidual:
    """A term's residual estimate.

    Attributes
    ----------
    relative, absolute : float or None
        ||I - T X||_F estimated, relative (/ sqrt of the kept pixels) and absolute;
        None when the run estimates no residual (:meth:`skipped`).
    XZ : ndarray, shape (n, p), or None
        X Z for the probes (None where no pixel is kept: nothing was multiplied, or
        where nothing was estimated).
    started : float
        ``time.perf_counter()`` when the estimate began (its time is reported).
    """

    relative: float | None
    absolute: float | None
    XZ: np.ndarray | None
    started: float

    @classmethod
    def skipped(cls) -> TermResidual:
        """No estimate: a run whose caller measures the terms' errors itself
        (:meth:`~.engine.InverseEngine._estimates_residual`)."""
        return cls(None, None, None, time.perf_counter())


@dataclass(frozen=True, eq=False)
class ProbedResidual:
    """The residual estimates of one run's terms.

    Attributes
    ----------
    matvecs : MatVecs
    Z : ndarray, shape (n, p)
        The probes (:func:`.residual.residual_probes` of ``seed``): what the probed
        passes' tasks multiply their rows of X_k - X_{k-1} by.
    seed : int
    """

    matvecs: MatVecs
    Z: np.ndarray
    seed: int

    @classmethod
    def for_run(cls, matvecs: MatVecs, seed: int) -> ProbedResidual:
        return cls(matvecs, residual_probes(matvecs.layout.fb, seed=seed), seed)

    def term_zero_XZ(self) -> np.ndarray:
        """X_0 Z = F^-1 Z, shape (n, p): known without a product."""
        return self.matvecs.layout.fb.apply_inverse(self.Z)

    def updated_XZ(self, XZ: np.ndarray | None, stats: list[BlockStats]) -> np.ndarray | None:
        """X_k Z, shape (n, p), from the held term's X_{k-1} Z and every row block's
        (X_k - X_{k-1}) Z, when the term's tasks all reported theirs; else None."""
        lay = self.matvecs.layout
        if XZ is None or len(stats) != lay.n_blocks or any(s.y is None for s in stats):
            return None
        XZ = XZ.copy()
        for s in stats:
            start = s.index * lay.tile_size
            XZ[start:start + s.y.shape[0]] += s.y
        return XZ

    def estimate(self, X, XZ: np.ndarray | None) -> TermResidual:
        """The residual of the term whose X is the store ``X``; ``XZ`` is X Z when known
        (else X is read to compute it; with it, ``X`` is not used and may be None)."""
        started = time.perf_counter()

        def apply_X(Z: np.ndarray) -> np.ndarray:
            nonlocal XZ
            if XZ is None:
                XZ = self.matvecs.apply_X(X, Z)
            return XZ

        relative, absolute = residual_of_probes(self.matvecs.apply_M, apply_X,
                                                self.matvecs.layout.fb, self.Z)
        return TermResidual(relative, absolute, XZ, started)
