"""bigT.spectral: the spectral radius from block products, checked against numpy's
eigenvalues, on the spectra that fool power iteration (a cluster of eigenvalues under
the top one, a +-rho pair)."""

import math

import numpy as np
import pytest

from bigT import config
from bigT.spectral import _collatz_wielandt, spectral_radius
from bigT.testing import clustered_spectrum


def test_dense_path_is_every_eigenvalue():
    rng = np.random.default_rng(0)
    M = rng.standard_normal((60, 60)) / 10  # complex top pair in general
    rho = spectral_radius(lambda V: M @ V, 60)
    assert rho.method == "dense" and rho.products == 60
    assert rho.value == pytest.approx(max(abs(np.linalg.eigvals(M))), rel=1e-12)
    assert 0 < rho.uncertainty < 1e-10


@pytest.mark.parametrize("top", [0.99, 1.02, 1.05])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_arnoldi_finds_the_top_of_a_cluster(top, seed):
    """The issue's reproducer: 2000 unknowns, 100 blocks with radii near 1, one above."""
    N, exact = clustered_spectrum(seed, top)
    rho = spectral_radius(lambda V: -(N @ V), N.shape[0], seed=seed)
    assert rho.method == "arnoldi" and rho.converged
    assert abs(rho.value - exact) <= max(rho.uncertainty, 1e-9)
    assert rho.uncertainty < config.SPECTRAL_RADIUS_RTOL
    assert (rho.upper >= 1) == (exact >= 1)


def test_plus_minus_pair_of_two_walls():
    """Two surfaces that only see each other: N = [[0, B], [C, 0]] has +-rho."""
    rng = np.random.default_rng(5)
    B, C = rng.uniform(0, 0.02, (300, 300)), rng.uniform(0, 0.02, (300, 300))
    N = np.block([[np.zeros((300, 300)), B], [C, np.zeros((300, 300))]])
    lam = np.linalg.eigvals(N)
    rho = spectral_radius(lambda V: N @ V, 600)
    assert rho.method == "arnoldi"
    assert rho.value == pytest.approx(max(abs(lam)), rel=1e-8)


def test_only_the_active_unknowns_count():
    d = np.array([0.5, 3.0, 0.25, 0.1] * 100)
    active = d < 1
    rho = spectral_radius(lambda V: d[:, None] * V, len(d), active)
    assert rho.value == pytest.approx(0.5, rel=1e-8)  # 3.0 sits on a left-out pixel
    assert spectral_radius(lambda V: V, 5, np.zeros(5, bool)).value == 0.0


def test_a_budget_too_small_is_not_converged_and_uncertain():
    N, _ = clustered_spectrum(0, 1.02)
    rho = spectral_radius(lambda V: N @ V, N.shape[0], max_products=20)
    assert not rho.converged and math.isinf(rho.uncertainty) and not rho.upper < 1
    assert "undetermined" in rho.describe()


# --- the Collatz-Wielandt bracket (M = -|M|) ------------------------------------------

def _exact(M, active=None):
    idx = np.arange(M.shape[0]) if active is None else np.flatnonzero(active)
    return max(abs(np.linalg.eigvals(M[np.ix_(idx, idx)])))


def _radius(M, active=None):
    """spectral_radius of a nonpositive M, told so."""
    return spectral_radius(lambda V: M @ V, M.shape[0], active, nonpositive=True)


def _bracket(A):
    """The bracket of a nonnegative A alone, whatever spectral_radius would take."""
    return _collatz_wielandt(lambda V: A @ V, A.shape[0])


def _perron(n, rho, seed, density=0.05):
    rng = np.random.default_rng(seed)
    N = rng.uniform(0, 1, (n, n)) * (rng.random((n, n)) < density)
    np.fill_diagonal(N, 0)
    return N * (rho / max(abs(np.linalg.eigvals(N))))


def _holds(rho, exact):
    return rho.value - rho.uncertainty <= exact <= rho.upper


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("rho_true", [0.3, 0.6, 0.9])
def test_bracket_holds_the_perron_root(seed, rho_true):
    N = _perron(400, rho_true, seed)
    rho = _bracket(N)
    assert _holds(rho, _exact(N))
    assert rho.products <= config.SPECTRAL_RADIUS_CW_MAX_PRODUCTS + 1


def test_a_low_narrow_bracket_is_taken_else_arnoldi_refines():
    low = _radius(-_perron(400, 0.3, 0))
    assert low.method == "collatz-wielandt" and low.upper <= config.SPECTRAL_RADIUS_CW_ACCEPT
    assert 2 * low.uncertainty <= config.SPECTRAL_RADIUS_CW_WIDE * low.upper
    N, exact = clustered_spectrum(0, 0.99)  # a crowded top near 1: the bracket stays wide
    near = spectral_radius(lambda V: -(N @ V), N.shape[0], nonpositive=True)
    assert near.method == "arnoldi" and abs(near.value - exact) <= max(near.uncertainty, 1e-9)
    assert near.uncertainty < config.SPECTRAL_RADIUS_RTOL
    # the bracket's products are counted with ARPACK's
    alone = spectral_radius(lambda V: -(N @ V), N.shape[0])
    assert near.products > alone.products


def test_bracket_of_two_walls_that_only_see_each_other():
    rng = np.random.default_rng(5)
    B, C = rng.uniform(0, 0.02, (300, 300)), rng.uniform(0, 0.02, (300, 300))
    N = np.block([[np.zeros((300, 300)), B], [C, np.zeros((300, 300))]]) / 4  # rho 0.75
    rho = _bracket(N)
    assert _holds(rho, _exact(N)) and rho.upper < 1


def test_a_crowded_top_is_bracketed():
    """The spectrum that fools power iteration's estimate from below: the bracket's
    upper bound comes from above, so it still holds the radius."""
    N, exact = clustered_spectrum(0, 0.95)
    rho = _bracket(N)
    assert _holds(rho, exact) and rho.upper < 1


def test_a_radius_above_one_is_held_above_one():
    """A narrow bracket above 1 is a certain divergence (the engine refuses it)."""
    M = -_perron(300, 1.02, 3, density=1.0)
    rho = _radius(M)
    assert rho.method == "collatz-wielandt"
    assert 1 < rho.value - rho.uncertainty and _holds(rho, _exact(M))


def test_bracket_counts_only_active_unknowns_and_a_zero_m():
    rng = np.random.default_rng(8)
    N = rng.uniform(0, 0.001, (500, 500))
    np.fill_diagonal(N, 0)
    active = np.ones(500, bool)
    active[::3] = False
    rho = _radius(-N, active)
    assert rho.method == "collatz-wielandt" and _holds(rho, _exact(-N, active))
    zero = spectral_radius(lambda V: 0 * V, 500, nonpositive=True)
    assert (zero.value, zero.upper, zero.method) == (0.0, 0.0, "collatz-wielandt")


def test_a_bracket_holding_one_goes_to_arnoldi():
    """A narrow bracket around 1 decides nothing: ARPACK's digits do."""
    M = -_perron(400, 1 - 1e-9, 2, density=0.02)
    assert _bracket(-M).value - _bracket(-M).uncertainty < 1 <= _bracket(-M).upper
    rho = _radius(M)
    assert rho.method == "arnoldi" and abs(rho.value - _exact(M)) <= rho.uncertainty + 1e-12
