"""bigT.spectral: the spectral radius from block products, checked against numpy's
eigenvalues, on the spectra that fool power iteration (a cluster of eigenvalues under
the top one, a +-rho pair)."""

import math

import numpy as np
import pytest

from bigT import config
from bigT.spectral import spectral_radius
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
