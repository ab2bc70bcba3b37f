"""The engine's products of M = I - T F^-1 and of a term's X with dense blocks, run on
the runner one task per row block (:func:`bigT.schedule.matvec.matvec`): the spectral
radius's products with M (or |M|), and the residual estimate's with M and X."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..schedule.matvec import matvec, matvec_spec
from ..schedule.runner import ClusterRunner, ThreadRunner, worker_path
from ..storage.channel_mixing import mixed_product
from .run_setup import RunLayout


@dataclass(frozen=True, eq=False)
class MatVecs:
    """Products with M and X through ``runner`` for the run laid out by ``layout``."""

    runner: ThreadRunner | ClusterRunner
    layout: RunLayout

    def apply_M(self, V: np.ndarray, largest: bool = False) -> np.ndarray:
        """M V, shape (n, p), for V of shape (n, p); with ``largest``, each row's
        largest entry of M instead, shape (n, 1) (V then only gives the shape)."""
        lay = self.layout
        spec = matvec_spec("largest-M" if largest else "matvec-M", lay.T_path, lay.n,
                           lay.tile_size, lay.T.dtype, memory=lay.policy, T=lay.T_path,
                           first_bounce=lay.fb.digest, zero_diagonal=lay.fb.zero_diagonal,
                           largest=largest)
        return matvec(self.runner, spec, V, lay.shared)

    def apply_abs_M(self, V: np.ndarray) -> np.ndarray:
        """|M| V, shape (n, p), for V of shape (n, p): the products of rho(M)'s upper
        bound rho(|M|) where M has entries of both signs (colour)."""
        lay = self.layout
        spec = matvec_spec("matvec-absM", lay.T_path, lay.n, lay.tile_size, lay.T.dtype,
                           memory=lay.policy, T=lay.T_path, first_bounce=lay.fb.digest,
                           zero_diagonal=lay.fb.zero_diagonal, absolute=True)
        return matvec(self.runner, spec, V, lay.shared)

    def m_nonpositive(self) -> bool:
        """Whether M = I - T F^-1 has no positive entry (a transport with no negative
        entry and F = diag T): known from the read of T's diagonal when it saw every
        entry (:attr:`.first_bounce.FirstBounce.m_nonpositive`: no pass); else one pass
        over M's rows (other first bounces, colour, a T with a negative entry, or a
        store whose diagonal was read from its diagonal tiles only)."""
        if self.layout.fb.m_nonpositive:
            return True
        largest = self.apply_M(np.zeros((self.layout.n, 1)), largest=True)
        return bool(largest.max(initial=0.0) <= 0.0)

    def apply_X(self, X, V: np.ndarray) -> np.ndarray:
        """X V, shape (n, p), for the term store ``X`` (its tiles read once, not
        cached: the next term replaces it)."""
        spec = matvec_spec("matvec-X", worker_path(X.path), X.shape[0], X.tile_size, X.dtype,
                           memory=self.layout.policy, cache_tiles=False)
        # a factored colour X (docs/FORMAT.md "Colour") is L S R; its tiles are S
        return mixed_product(getattr(X, "mixing", None),
                             lambda W: matvec(self.runner, spec, np.ascontiguousarray(W)), V)
