"""The residual estimate ||I - T X||_F of an inverse X from Rademacher probes.

With p = ``config.RESIDUAL_PROBES`` probes z (z_i = +-1 on the pixels kept, 0 elsewhere)
and r = z - T (X z): since E[z z^T] = D (the kept pixels' diagonal),
E||r||^2 = ||(I - T X) D||_F^2, so (1/p) sum ||r||^2 is an unbiased estimate of its
square. The relative value ||I - T X||_F / sqrt(n_kept) is the rms of the columns of
I - T X (what ``tol`` is compared with). T (X z) is computed as u - M u with u = F X z,
the same T on the kept pixels. The same probes serve every term of a run, so that two
terms' estimates compare exactly.
"""

from __future__ import annotations

import math

import numpy as np

from .. import config
from .first_bounce import FirstBounce


def residual_probes(fb: FirstBounce, probes=None, seed=0) -> np.ndarray:
    """The Rademacher probes Z of :func:`estimate_residual`, shape (n, p): +-1 on the
    kept pixels, 0 elsewhere; the same for the same ``seed``."""
    p = probes or config.RESIDUAL_PROBES
    rng = np.random.default_rng(seed + 7919)
    return rng.choice(np.array([-1.0, 1.0]), size=(len(fb.active), p)) * fb.active[:, None]


def estimate_residual(apply_M, apply_X, fb: FirstBounce, probes=None,
                      seed=0) -> tuple[float, float]:
    """(relative, absolute) estimate of ||I - T X||_F (module docstring).

    Parameters
    ----------
    apply_M, apply_X : callable
        Multiply M = I - T F^-1 and X by (n, p) blocks; ``apply_X`` is called once,
        with :func:`residual_probes` of the same ``probes`` and ``seed``.
    fb : FirstBounce
    probes : int, optional
        p (``config.RESIDUAL_PROBES``).
    seed : int

    Returns
    -------
    (float, float)
        Relative (absolute / sqrt(number of kept pixels)) and absolute.
    """
    return residual_of_probes(apply_M, apply_X, fb, residual_probes(fb, probes, seed))


def residual_of_probes(apply_M, apply_X, fb: FirstBounce, Z: np.ndarray) -> tuple[float, float]:
    """:func:`estimate_residual` with its probes given, Z of shape (n, p) (the engine
    makes them once per run: :mod:`.probes`)."""
    n_act = int(fb.active.sum())
    if n_act == 0:
        return 0.0, 0.0
    p = Z.shape[1]
    U = fb.apply(apply_X(Z))
    R = Z - (U - apply_M(U))  # T (X z) = u - M u with u = F X z, on the kept pixels
    abs_ = math.sqrt(float(np.sum(R * R)) / p)
    return abs_ / math.sqrt(n_act), abs_
