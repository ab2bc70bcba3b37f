"""The spectral radius of an operator given only by its products, with its uncertainty.

The stratified series (paper eq. 13) converges when rho(M) < 1, M = I - T F^-1, and
its error after k terms shrinks like rho(M)^k; scenes report rho as ground truth. Both
see M (or T) only through products with blocks of vectors, each of which streams the
matrix from disk, so the estimator below asks for few of them:

* up to ``config.SPECTRAL_RADIUS_DENSE_MAX`` unknowns, the whole matrix is formed with
  one block product (the identity's columns) and its eigenvalues computed densely;
* above, ARPACK's implicitly restarted Arnoldi (``scipy.sparse.linalg.eigs``) finds the
  ``config.SPECTRAL_RADIUS_RITZ`` eigenvalues of largest modulus. Arnoldi is used rather
  than the power method because a transport matrix's spectrum often has several
  eigenvalues near the top (one per weakly coupled surface, or a +-rho pair when two
  walls only see each other): there power iteration converges slowly and from below,
  and 30 of its steps can report 0.99 for a matrix whose radius is 1.02.

The uncertainty reported is the residual ||M x - lambda x|| / ||x|| of the Ritz pair of
largest modulus, checked with one more block product: lambda is an exact eigenvalue of a
matrix within that distance of M (for a normal M, an eigenvalue of M lies within it).

A cheaper, rigorous bracket where the caller knows that M has no positive entry
(``nonpositive``; the engine checks M's rows): a physical transport has no negative
entry, so with F = diag T, M = -|M|, and rho(M) is the Perron root of the nonnegative
A = -M. For any v > 0 (Collatz-Wielandt), rho <= max_i (A v)_i / v_i, and for any
x >= 0, x != 0, A x >= lambda x implies rho >= lambda (subinvariance). Shifted power
steps v <- A v + s v make v the Perron vector; the upper bound falls to rho in a few
steps (16 products: 0.26567 for the dense 384x512 corner's 0.26538, where ARPACK took
132), the lower bound is taken on x = v restricted to the pixels where v is not
negligible (the others would hold it at 0), at several cuts of "negligible" in one
block product (the best bound kept). The result is reported as the bracket's
middle +- its half-width, so ``upper`` is the rigorous upper bound (widened by the
rounding of float32 entries: the products of M may come from its stored rows or from
T's rows times F^-1, which agree to that). It is taken when it is narrow
(``config.SPECTRAL_RADIUS_CW_RTOL``), or its top is low
(``config.SPECTRAL_RADIUS_CW_ACCEPT``) and its width at most
``config.SPECTRAL_RADIUS_CW_WIDE``, and does not hold 1; near 1, where the error's
rate 1 - rho needs rho's digits, or beyond, ARPACK decides, as above (its products
counted with the bracket's).

An upper bound where M has entries of both signs (``apply_abs``: products with |M|,
M's entries' absolute values). A colour transport's F^-1 (the inverses of the pixels'
3x3 colour-mixing blocks) has negative entries, so M = I - T F^-1 has positive ones
and the bracket above does not apply to M; but |lambda| <= rho(|M|) for every
eigenvalue lambda of M (Wielandt: |M x| <= |M| |x| entrywise, and |M| >= 0 is
monotone), and the bracket does apply to the nonnegative |M|. Its top is a rigorous
upper bound on rho(M), enough for the series' convergence and for the rate at which
its error falls; its bottom bounds rho(|M|), not rho(M), from below. The iteration
narrows the bracket to ``config.SPECTRAL_RADIUS_CW_RTOL`` whatever its height (only the
top is used), so the bound is rho(|M|) to about 2 %; rho(|M|) exceeds rho(M) where
signs cancel in M: by about 0.75 of the pixel-to-pixel variation of the colour mixing
(2 % for a 2 % variation, 8 % for 10 %: tests/test_spectral.py), some 10 % where the
bands' albedos differ as well (tests/algorithms/test_colour_inverse.py), more under
strong cross-talk that varies. It is taken (method ``"collatz-wielandt-abs"``)
when its top is under ``config.SPECTRAL_RADIUS_ABS_ACCEPT``; above, ARPACK computes
rho(M) itself as for any operator, the bracket's products counted with its own.

Which estimator runs, and what its number means:

============================  ==========================================  ===============
when                          estimator                                   uncertainty
============================  ==========================================  ===============
at most DENSE_MAX unknowns    every eigenvalue (``"dense"``)              rounding
M has no positive entry       Collatz-Wielandt on -M, taken when narrow   the bracket
                              or low (``"collatz-wielandt"``)             (rigorous)
M of both signs, given |M|    Collatz-Wielandt on |M|, taken when its     an upper bound
                              top is under ABS_ACCEPT                     (rigorous); rho
                              (``"collatz-wielandt-abs"``)                may be lower
otherwise, or undecided       ARPACK (``"arnoldi"``)                      Ritz residual
============================  ==========================================  ===============
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from . import config

#: apply(V) multiplies the operator by V of shape (n, p) and returns (n, p).
BlockProduct = Callable[[np.ndarray], np.ndarray]

#: The method name of the upper bound rho(M) <= rho(|M|) (module docstring).
ABS_BOUND = "collatz-wielandt-abs"


@dataclass(frozen=True)
class SpectralRadius:
    """An estimate of rho = max |lambda| of an operator.

    Attributes
    ----------
    value : float
        The estimate (the largest modulus of the Ritz values).
    uncertainty : float
        The Ritz residual ||M x - value x|| / ||x|` (``inf`` when the solver did not
        converge): rho is believed to lie within ``value +- uncertainty``.
    products : int
        Operator products it took (one per vector; a block of p vectors counts p).
    method : str
        ``"dense"``, ``"collatz-wielandt"``, ``"collatz-wielandt-abs"`` (value +-
        uncertainty brackets rho(|M|), whose top bounds rho(M) from above),
        ``"arnoldi"`` or ``"zero"`` (no unknowns).
    converged : bool
    """

    value: float
    uncertainty: float
    products: int
    method: str
    converged: bool = True

    @property
    def upper(self) -> float:
        """The largest radius the estimate allows: value + uncertainty."""
        return self.value + self.uncertainty

    def describe(self) -> str:
        if self.method == "zero":
            return "0 (no pixels)"
        if not self.converged:
            return (f"undetermined (ARPACK did not converge in {self.products} products"
                    + ("" if math.isnan(self.value) else f"; at least {self.value:.4f}") + ")")
        if self.method == ABS_BOUND:
            return (f"at most {self.upper:.4f} (rho(|M|) in [{self.value - self.uncertainty:.4f}, "
                    f"{self.upper:.4f}], {self.method}, {self.products} products)")
        return (f"{self.value:.4f} +- {self.uncertainty:.1e} "
                f"({self.method}, {self.products} products)")

    def meaning(self) -> str:
        """What ``value +- uncertainty`` is, in words: an eigenvalue computed to
        convergence (dense, ARPACK) and a Collatz-Wielandt bracket are not the same
        kind of number, and the two may differ by the bracket's half-width."""
        return spectral_meaning(self.method, self.value, self.uncertainty)


def spectral_meaning(method: str | None, value: float | None,
                     uncertainty: float | None) -> str:
    """:meth:`SpectralRadius.meaning` from the recorded ``method``, ``value`` and
    ``uncertainty`` (a store's record, a scene's summary; None when not recorded)."""
    if uncertainty is not None and not math.isfinite(uncertainty):
        return "undetermined: ARPACK did not converge"
    if method == "collatz-wielandt" and value is not None and uncertainty is not None:
        return (f"a rigorous Collatz-Wielandt bracket [{value - uncertainty:.4f}, "
                f"{value + uncertainty:.4f}] on rho, enough to tell that the series "
                "converges, not rho to these digits")
    if method == ABS_BOUND and value is not None and uncertainty is not None:
        return (f"rho(M) <= rho(|M|) in [{value - uncertainty:.4f}, {value + uncertainty:.4f}] "
                "(Collatz-Wielandt on |M|; rigorous upper bound, M is not sign-definite): "
                "the series converges and its error falls at least that fast per term; "
                "rho(M) itself may be lower")
    if method == "arnoldi":
        return ("the largest eigenvalue modulus, computed by ARPACK to convergence "
                "(+- its Ritz residual)")
    if method == "dense":
        return "the largest eigenvalue modulus, every eigenvalue computed (+- rounding)"
    if method == "zero":
        return "no pixels"
    return "an estimate recorded without its method (by an older bigT)"


def spectral_radius(apply: BlockProduct, n: int, active: np.ndarray | None = None,
                    rtol: float | None = None, max_products: int | None = None,
                    seed: int = 0, nonpositive: bool = False,
                    apply_abs: BlockProduct | None = None) -> SpectralRadius:
    """rho of the operator ``apply`` restricted to the unknowns ``active``.

    Parameters
    ----------
    apply : callable
        ``apply(V)``, V of shape (n, p) float64 (zero outside ``active``), returns the
        product, shape (n, p).
    n : int
    active : ndarray of bool, shape (n,), optional
        The unknowns the operator acts on (all when omitted).
    rtol : float, optional
        ARPACK's relative tolerance on the Ritz values
        (``config.SPECTRAL_RADIUS_RTOL``).
    max_products : int, optional
        Give up (``converged=False``) after about this many products
        (``config.SPECTRAL_RADIUS_MAX_PRODUCTS``).
    seed : int
        Seed of ARPACK's starting vector.
    nonpositive : bool
        The caller knows that no entry of the operator is positive: the
        Collatz-Wielandt bracket (module docstring) is tried before ARPACK.
    apply_abs : callable, optional
        ``apply_abs(V)``: the product with |M| (the operator's entries' absolute
        values), as ``apply``. Where the operator is not known to be nonpositive, the
        bracket of rho(|M|) is tried first, its top taken as an upper bound on rho
        when under ``config.SPECTRAL_RADIUS_ABS_ACCEPT`` (module docstring).

    Returns
    -------
    SpectralRadius
    """
    idx = np.arange(n) if active is None else np.flatnonzero(active)
    m = len(idx)
    if m == 0:
        return SpectralRadius(0.0, 0.0, 0, "zero")

    def restricted(product: BlockProduct) -> BlockProduct:
        def on_active(V_active: np.ndarray) -> np.ndarray:
            V = np.zeros((n, V_active.shape[1]))
            V[idx] = V_active
            return np.asarray(product(V), dtype=np.float64)[idx]
        return on_active

    apply_active = restricted(apply)
    if m <= max(config.SPECTRAL_RADIUS_DENSE_MAX, 3):  # ARPACK needs k < m - 1
        return _dense(apply_active, m)
    spent = 0
    if nonpositive:
        bracket = _collatz_wielandt(lambda V: -apply_active(V), m)
        if _narrow_enough(bracket.upper, bracket.upper - 2 * bracket.uncertainty):
            return bracket
        spent = bracket.products
    elif apply_abs is not None:
        bound = _abs_bound(restricted(apply_abs), m)
        if bound.upper < config.SPECTRAL_RADIUS_ABS_ACCEPT:
            return bound
        spent = bound.products
    rho = _arnoldi(apply_active, m,
                   config.SPECTRAL_RADIUS_RTOL if rtol is None else rtol,
                   config.SPECTRAL_RADIUS_MAX_PRODUCTS if max_products is None
                   else max_products, seed)
    return dataclasses.replace(rho, products=rho.products + spent)


def _narrow_enough(hi: float, lo: float) -> bool:
    """Whether the bracket [lo, hi] is narrow, or low and not too wide (module
    docstring), and on one side of 1 (which decides whether the series converges)."""
    if lo < 1 <= hi:
        return False
    return (hi - lo <= config.SPECTRAL_RADIUS_CW_RTOL * hi
            or (hi <= config.SPECTRAL_RADIUS_CW_ACCEPT
                and hi - lo <= config.SPECTRAL_RADIUS_CW_WIDE * hi))


def _dense(apply_active: BlockProduct, m: int) -> SpectralRadius:
    """All m columns at once, then every eigenvalue: exact to rounding."""
    M = apply_active(np.eye(m))
    lam = np.linalg.eigvals(M)
    value = float(np.abs(lam).max())
    rounding = m * np.finfo(np.float64).eps * float(np.abs(M).sum(axis=1).max(initial=0.0))
    return SpectralRadius(value, rounding, m, "dense")


#: Relative rounding of an operator's entries stored in float32 (two of its units):
#: the bracket is widened by it.
_ENTRY_ROUNDING = 2 * float(np.finfo(np.float32).eps)


def _collatz_wielandt(apply_nonneg: BlockProduct, m: int,
                      done: Callable[[float, float], bool] | None = None,
                      max_passes: int | None = None) -> SpectralRadius:
    """rho of a nonnegative operator A (``apply_nonneg`` multiplies it by (m, k)
    blocks) bracketed by Collatz-Wielandt bounds (module docstring): value +-
    uncertainty is the bracket. The iteration stops once ``done(hi, lo)``
    (:func:`_narrow_enough` by default) or after ``max_passes`` block products
    (default :func:`_passes_allowed`); ``products`` counts their vectors."""
    done = _narrow_enough if done is None else done
    v = np.ones(m)
    w = apply_nonneg(v[:, None])[:, 0]  # A v, shape (m,)
    if not w.any():
        return SpectralRadius(0.0, 0.0, 1, "collatz-wielandt")
    passes, products, hi, lo = 1, 1, float((w / v).max()), 0.0
    while passes < (_passes_allowed(hi) if max_passes is None else max_passes):
        v = w + config.SPECTRAL_RADIUS_CW_SHIFT * hi * v
        v /= v.max()
        w = apply_nonneg(v[:, None])[:, 0]
        passes += 1
        products += 1
        hi = min(hi, float((w / v).max()))
        if passes >= 8 and passes % 4 == 0:
            bound, columns = _subinvariant_bound(apply_nonneg, v)
            lo = max(lo, bound)
            passes += 1
            products += columns
            if done(hi, lo):
                break
    # the sums' rounding (as in _dense) and float32 entries' (module docstring)
    rounding = m * np.finfo(np.float64).eps + _ENTRY_ROUNDING
    hi *= 1 + rounding
    lo *= 1 - rounding
    return SpectralRadius((hi + lo) / 2, (hi - lo) / 2, products, "collatz-wielandt")


def _passes_allowed(hi: float) -> int:
    """The bracket's block products allowed while its top is ``hi`` (the last may be
    followed by one lower-bound pass): more while the top is low
    (``config.SPECTRAL_RADIUS_CW_ACCEPT``), where the lower bound lags behind only on
    the pixels the power steps reach last (the open Cornell box's: its bracket closed
    after 33 passes, where ARPACK took 53 more products after 25); near 1, where
    ARPACK decides anyway, the usual few."""
    if hi <= config.SPECTRAL_RADIUS_CW_ACCEPT:
        return config.SPECTRAL_RADIUS_CW_MAX_PASSES_LOW
    return config.SPECTRAL_RADIUS_CW_MAX_PASSES


def _abs_bound(apply_abs_active: BlockProduct, m: int) -> SpectralRadius:
    """The Collatz-Wielandt bracket of rho(|M|) (``apply_abs_active`` multiplies |M| by
    (m, k) blocks): its top bounds rho(M) from above (module docstring)."""
    # only the top matters (it is the bound reported): the bracket is narrowed
    # whatever its height, not left wide when low as rho's own bracket may be; and
    # its low top is taken as it stands (under ABS_ACCEPT), so no more passes than
    # the usual are spent narrowing it
    bracket = _collatz_wielandt(apply_abs_active, m,
                                lambda hi, lo: hi - lo <= config.SPECTRAL_RADIUS_CW_RTOL * hi,
                                max_passes=config.SPECTRAL_RADIUS_CW_MAX_PASSES)
    return dataclasses.replace(bracket, method=ABS_BOUND)


def _subinvariant_bound(apply_nonneg: BlockProduct, v: np.ndarray) -> tuple[float, int]:
    """lambda with A x >= lambda x for x = v (shape (m,), > 0) restricted to the pixels
    where v is at least a fraction c of its largest entry (0 elsewhere), the best over
    the fractions c of ``config.SPECTRAL_RADIUS_CW_SUPPORTS``: a lower bound on
    rho(A), each x being >= 0 and nonzero (v's largest entry passes every c <= 1).
    One block product, one column per fraction; returns (lambda, its columns).

    Why several: a pixel kept whose neighbours were cut loses their share of A x and
    pulls the bound down, while a pixel A barely reaches (v decaying towards 0 with
    each step) holds it near 0. Which cut sits between the two depends on the scene:
    1 % suits the wall corners, but on the paper's open Cornell box (a fifth of the
    patches see nothing) it stalled at 0.278 for rho = 0.361, and ARPACK then took 53
    more products; 1e-9 there gives 0.337 after 33 passes (1e-4 and 1e-6 as well
    changed no stop on the box or the corners)."""
    fractions = np.asarray(config.SPECTRAL_RADIUS_CW_SUPPORTS, dtype=np.float64)
    if not np.all((fractions > 0) & (fractions <= 1)):
        raise ValueError(f"config.SPECTRAL_RADIUS_CW_SUPPORTS must lie in (0, 1], got "
                         f"{config.SPECTRAL_RADIUS_CW_SUPPORTS}")
    on = v[:, None] >= fractions[None, :] * v.max()  # (m, c)
    X = np.where(on, v[:, None], 0.0)
    Y = apply_nonneg(X)
    best = 0.0
    for j in range(len(fractions)):
        kept = on[:, j]
        best = max(best, float((Y[kept, j] / X[kept, j]).min()))
    return best, len(fractions)


def _arnoldi(apply_active: BlockProduct, m: int, rtol: float, max_products: int,
             seed: int) -> SpectralRadius:
    # scipy.sparse.linalg (ARPACK): ~0.17 s, only when the dense and bracket paths
    # cannot decide
    from scipy.sparse.linalg import ArpackError, ArpackNoConvergence, LinearOperator, eigs

    v0 = np.random.default_rng(seed).standard_normal(m)
    if not np.any(apply_active(v0[:, None])):
        # M v0 = 0 for a random v0: M = 0 (convex or flat scenes: no interreflection),
        # where ARPACK stops on a zero Krylov vector
        return SpectralRadius(0.0, 0.0, 1, "arnoldi")
    count = [1]

    def matvec(x):
        count[0] += 1
        return apply_active(np.asarray(x, dtype=np.float64).reshape(m, 1))[:, 0]

    k = min(config.SPECTRAL_RADIUS_RITZ, m - 2)
    ncv = min(m, max(2 * k + 1, config.SPECTRAL_RADIUS_NCV))
    op = LinearOperator((m, m), matvec=matvec, dtype=np.float64)
    restarts = max(1, max_products // max(1, ncv - k))
    try:
        lam, vec = eigs(op, k=k, which="LM", ncv=ncv, tol=rtol, v0=v0, maxiter=restarts)
    except ArpackNoConvergence as exc:
        # the largest modulus converged, if any, is only a lower bound: rho stays unknown
        lam = exc.eigenvalues
        value = float(np.abs(lam).max()) if len(lam) else math.nan
        return SpectralRadius(value, math.inf, count[0], "arnoldi", converged=False)
    except ArpackError:  # a breakdown ARPACK does not recover from: unknown as well
        return SpectralRadius(math.nan, math.inf, count[0], "arnoldi", converged=False)
    value, residual = _largest(lam, vec, apply_active)
    return SpectralRadius(value, residual, count[0] + 2, "arnoldi")


def _largest(lam: np.ndarray, vec: np.ndarray, apply_active: BlockProduct):
    """The largest |lambda| and its Ritz residual ||M x - lambda x|| / ||x|| (one block
    product of the real and imaginary parts of x)."""
    j = int(np.argmax(np.abs(lam)))
    x = vec[:, j]
    MX = apply_active(np.stack([x.real, x.imag], axis=1))
    r = (MX[:, 0] + 1j * MX[:, 1]) - lam[j] * x
    return float(abs(lam[j])), float(np.linalg.norm(r) / np.linalg.norm(x))
