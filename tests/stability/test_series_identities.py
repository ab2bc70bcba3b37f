"""Property-based tests (hypothesis) of the series identities, on tiny random T.

* Paper eq. 14: the binomial form F^-1 sum_l C(n+1, l+1) (-T F^-1)^l equals eq. 13's
  power form. bigT computes eq. 13 (power and Horner); the reference here is eq. 14,
  evaluated densely with numpy, sharing nothing with bigT.
* Newton-Schulz X <- X (2I - T X) from X_0 = F^-1: after j steps it is the power
  form at 2^j - 1 terms, i.e. bigT's newton-schulz at j steps equals bigT's power
  method at 2^j - 1 terms (and both equal the dense reference).

M has random signs (T may hold negative entries), a zero diagonal (F = diag T) and a
radius drawn in [0, 0.9]; T is 2 to 6 pixels in tiles of 2 or 8.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from stability_helpers import (
    binomial_form,
    invert,
    power_form,
    read_dense,
    scratch_dir,
    spectral_radius,
    write_store,
)

EPS = float(np.finfo(np.float64).eps)


def examples(n):
    """Hypothesis settings for n examples: few by default, as each one runs the engine
    (0.3 s for the binomial check, 0.8 s for Newton-Schulz); more in the slow run."""
    return settings(max_examples=n, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow])


@st.composite
def small_transports(draw):
    """(T, f, tile size): T = (I - M) diag(f), rho(M) = rho drawn, ||M||_2 <= 3 (a
    very non-normal M would only measure the reference's own rounding)."""
    n = draw(st.integers(2, 6))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    low = draw(st.sampled_from([0.0, -1.0]))  # nonnegative M, or mixed signs
    M = rng.uniform(low, 1.0, (n, n))
    np.fill_diagonal(M, 0.0)
    r = spectral_radius(M)
    assume(r > 1e-3)
    M *= draw(st.floats(0.0, 0.9)) / r
    assume(np.linalg.norm(M, 2) <= 3)
    f = rng.uniform(0.2, 5.0, n)
    return (np.eye(n) - M) * f[None, :], f, draw(st.sampled_from([2, 8]))


def tolerance(T, f, terms):
    """Rounding of either form: the binomial sum's terms reach (1 + ||T F^-1||)^(n+1)
    before they cancel, times max F^-1, times a margin of 1000 ulps."""
    g = np.linalg.norm(T / f[None, :], 2)
    return 1e3 * EPS * (1 + g) ** (terms + 1) / f.min()


def check_binomial(case, terms, method):
    T, f, tile = case
    with scratch_dir() as d:
        rep = invert(write_store(T, d / "T.zarr", tile_size=tile), d / "X.zarr", terms,
                     method=method)
        X = read_dense(d / "X.zarr")
    assert rep.terms == terms
    np.testing.assert_allclose(X, binomial_form(T, terms), rtol=0,
                               atol=tolerance(T, f, terms))


def check_newton_schulz(case, steps):
    T, f, tile = case
    held = 2**steps - 1
    with scratch_dir() as d:
        store = write_store(T, d / "T.zarr", tile_size=tile)
        rep = invert(store, d / "NS.zarr", held, method="newton-schulz")
        invert(store, d / "P.zarr", held, method="power")
        X_ns, X_p = read_dense(d / "NS.zarr"), read_dense(d / "P.zarr")
    assert rep.terms == held
    # one record per step, unless M = 0 ended the series at once (rho drawn 0)
    assert len(rep.history) == steps + 1 or rep.stopped.startswith("series exhausted")
    atol = tolerance(T, f, held)
    np.testing.assert_allclose(X_ns, X_p, rtol=0, atol=atol)
    np.testing.assert_allclose(X_ns, power_form(T, held), rtol=0, atol=atol)


CASES = dict(case=small_transports(), terms=st.integers(0, 5),
             method=st.sampled_from(["power", "horner"]))


@examples(10)
@given(**CASES)
def test_binomial_form_equals_power_form(case, terms, method):
    check_binomial(case, terms, method)


@pytest.mark.slow
@examples(40)
@given(**CASES)
def test_binomial_form_equals_power_form_thorough(case, terms, method):
    check_binomial(case, terms, method)


@examples(4)
@given(case=small_transports(), steps=st.integers(1, 3))
def test_newton_schulz_equals_power_form_at_2j_minus_1(case, steps):
    check_newton_schulz(case, steps)


@pytest.mark.slow
@examples(25)
@given(case=small_transports(), steps=st.integers(1, 3))
def test_newton_schulz_equals_power_form_at_2j_minus_1_thorough(case, steps):
    check_newton_schulz(case, steps)
