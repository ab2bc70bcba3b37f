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
    # a lower bound's pass is one vector a support
    supports = len(config.SPECTRAL_RADIUS_CW_SUPPORTS)
    assert rho.products <= supports * (config.SPECTRAL_RADIUS_CW_MAX_PASSES_LOW + 1)


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


def _open_cornell_box_m(tmp_path):
    """M = I - T F^-1 (F = diag T) of the paper's open Cornell box at 24x30 patches,
    with bench_paper's density for that size: a fifth of its patches see nothing, and
    its four top eigenvalues lie within 0.1 % of each other."""
    import scipy.sparse as sp

    import bigT

    scale = 5120 / (24 * 30)
    scene = bigT.scenes.cornell(size=(24, 30), path=tmp_path / "box.zarr", preview=False,
                                progress=False, ff_cut=5e-4 * scale, threshold=1.1e-4 * scale)
    T = scene.T.to_scipy().tocsr().astype(np.float64)
    M = -(T @ sp.diags(1 / T.diagonal())).toarray()
    np.fill_diagonal(M, 0)
    return M


def test_the_open_cornell_box_is_bracketed_without_arnoldi(tmp_path, monkeypatch):
    """The lower bound over several supports: with the corners' 1 % cut alone, the
    box's bracket stalled well under rho and ARPACK took over (80 products in all)."""
    M = _open_cornell_box_m(tmp_path)
    rho = _radius(M)
    assert rho.method == "collatz-wielandt" and _holds(rho, _exact(M))
    supports = len(config.SPECTRAL_RADIUS_CW_SUPPORTS)
    assert rho.products <= supports * (config.SPECTRAL_RADIUS_CW_MAX_PASSES_LOW + 1)
    monkeypatch.setattr(config, "SPECTRAL_RADIUS_CW_SUPPORTS", (1e-2,))
    one_cut = _radius(M)
    assert one_cut.method == "arnoldi" and one_cut.products > 2 * rho.products


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


# --- the upper bound rho(M) <= rho(|M|) (M of both signs: colour) --------------------

#: Camera sensitivities and projector primaries with a real device's cross-talk (as in
#: tests/algorithms/test_colour_inverse.py).
_CAMERA = np.array([[0.80, 0.15, 0.05], [0.10, 0.80, 0.10], [0.05, 0.20, 0.75]])
_PROJECTOR = np.array([[0.90, 0.10, 0.00], [0.08, 0.85, 0.07], [0.02, 0.10, 0.88]])


def _colour_m(pixels, rho_grey, seed, spread=0.1, mixing=_CAMERA @ _PROJECTOR):
    """M = I - T F^-1 of a colour T = (per-pixel gain) kron(K_grey, mixing) + its
    diagonal blocks: F = T's 3x3 diagonal blocks, so M's diagonal blocks are 0 and its
    off-diagonal ones are -T_pq F_q^-1, of both signs (F_q^-1 has negative entries)."""
    rng = np.random.default_rng(seed)
    K = _perron(pixels, rho_grey, seed, density=0.1)
    np.fill_diagonal(K, 1.0)
    gain = (1 + spread * rng.standard_normal((pixels, 3, 3))).clip(0.5)
    T = np.einsum("pq,pij->piqj", K, gain * mixing).reshape(3 * pixels, 3 * pixels)
    F = np.zeros_like(T)
    for p in range(pixels):
        F[3 * p:3 * p + 3, 3 * p:3 * p + 3] = T[3 * p:3 * p + 3, 3 * p:3 * p + 3]
    M = np.eye(3 * pixels) - T @ np.linalg.inv(F)
    for p in range(pixels):
        M[3 * p:3 * p + 3, 3 * p:3 * p + 3] = 0.0  # I - F_p F_p^-1, rounding dropped
    return M


def _with_abs(M, active=None):
    return spectral_radius(lambda V: M @ V, M.shape[0], active,
                           apply_abs=lambda V: np.abs(M) @ V)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("rho_grey", [0.2, 0.5])
@pytest.mark.parametrize("spread,slack", [(0.02, 1.03), (0.05, 1.05), (0.1, 1.1)])
def test_abs_bound_is_above_every_eigenvalue_and_tight_for_small_cross_talk(
        seed, rho_grey, spread, slack):
    """rho(M) = rho_grey here (M is similar to the grey one); the bound's excess comes
    from the pixels' mixing varying (``spread``): about 0.75 of it."""
    M = _colour_m(150, rho_grey, seed, spread=spread)
    assert M.max() > 0 and M.min() < 0  # not sign-definite: the plain bracket is out
    exact = _exact(M)
    rho = _with_abs(M)
    assert rho.method == "collatz-wielandt-abs"
    assert exact <= rho.upper <= slack * exact
    # and it brackets rho(|M|) itself, the number it bounds
    assert _holds(rho, _exact(np.abs(M)))
    supports = len(config.SPECTRAL_RADIUS_CW_SUPPORTS)
    assert rho.products <= supports * (config.SPECTRAL_RADIUS_CW_MAX_PASSES + 1)
    assert "rigorous upper bound" in rho.meaning() and "at most" in rho.describe()


def test_abs_bound_holds_under_strong_cross_talk():
    """Cross-talk that cancels in M leaves the bound loose, never below rho."""
    rng = np.random.default_rng(4)
    mixing = np.eye(3) + 0.4 * rng.uniform(-1, 1, (3, 3))
    M = _colour_m(120, 0.3, 4, spread=0.3, mixing=mixing)
    rho = _with_abs(M)
    assert rho.upper >= _exact(M)


def test_abs_bound_near_one_goes_to_arnoldi():
    """A bound at or above ABS_ACCEPT tells too little (rho(M) may be far lower, or the
    bound may hold 1 while rho does not): ARPACK computes rho, the bound's products
    counted with its own."""
    M = _colour_m(150, 0.95, 0)
    bound = _collatz_wielandt(lambda V: np.abs(M) @ V, M.shape[0])
    assert bound.upper >= config.SPECTRAL_RADIUS_ABS_ACCEPT
    rho = _with_abs(M)
    assert rho.method == "arnoldi" and rho.converged
    assert abs(rho.value - _exact(M)) <= max(rho.uncertainty, 1e-9)
    assert rho.products > bound.products


def test_abs_bound_counts_only_active_unknowns():
    M = _colour_m(150, 0.3, 1)
    active = np.ones(M.shape[0], bool)
    active[:90] = False
    M[3:6, 60:63] = 50.0  # a large entry in a left-out row: ignored
    rho = _with_abs(M, active)
    assert rho.method == "collatz-wielandt-abs"
    assert _exact(M, active) <= rho.upper <= 1.1 * _exact(M, active)
