"""A diverging series is never accepted: the spectral radius estimate refuses it up
front, and a residual that grows from one term to the next stops the run even when the
estimate was fooled, keeping the last good term."""

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT.algorithms import divergence
from bigT.spectral import SpectralRadius
from bigT.testing import clustered_spectrum

from inverse_helpers import dense, dense_stratified


def block_transport(seed, top, blocks, **kw):
    """T = I + N (bigT.testing.clustered_spectrum): M = I - T diag(T)^-1 = -N, whose
    radius is ``top``, with the other blocks' radii crowding under it."""
    N, _ = clustered_spectrum(seed, top, blocks, **kw)
    return sp.csr_array(sp.identity(N.shape[0]) + N)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("top", [1.02, 1.05])
def test_the_issue_reproducer_is_refused(tmp_path, top, seed):
    """2000 x 2000, 100 blocks near the top of the spectrum: power iteration said 0.99."""
    T = bigT.from_scipy(block_transport(seed, top, 100), tmp_path / "T.zarr", tile_size=512,
                        dtype="float64")
    with pytest.raises(bigT.DivergenceError, match="may be >= 1"):
        bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=4, progress=False)
    assert not (tmp_path / "X.zarr").exists()


def test_a_radius_just_below_one_runs(tmp_path):
    T = bigT.from_scipy(block_transport(0, 0.99, 100), tmp_path / "T.zarr", tile_size=512,
                        dtype="float64")
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=2, prune=0, progress=False)
    assert rep.spectral_radius == pytest.approx(0.99, abs=1e-6)
    assert rep.spectral_uncertainty < 1e-4


def test_a_growing_residual_stops_the_run_and_keeps_the_last_good_term(tmp_path, monkeypatch):
    """An estimator fooled into 0.5: the residual check alone must stop the run."""
    A = block_transport(1, 1.05, 10, low=0.3, high=0.6).toarray()
    T = bigT.from_scipy(sp.csr_array(A), tmp_path / "T.zarr", tile_size=64, dtype="float64")
    monkeypatch.setattr(divergence, "spectral_radius",
                        lambda *a, **k: SpectralRadius(0.5, 0.0, 1, "fooled"))
    X = tmp_path / "X.zarr"
    with pytest.raises(bigT.DivergenceError, match="residual grew") as err:
        bigT.stratified_inverse(T, X, terms=40, prune=0, progress=False)
    kept = int(str(err.value).split("The inverse keeps term ")[1].split(";")[0])
    assert 1 <= kept < 40
    np.testing.assert_allclose(dense(X), dense_stratified(A, kept), rtol=1e-10, atol=1e-12)
    # forced, the same run goes on past it
    rep = bigT.stratified_inverse(T, X, terms=kept + 2, prune=0, progress=False, force=True)
    assert rep.terms == kept + 2


def test_no_interreflection_has_radius_zero_beyond_the_dense_path(tmp_path):
    """M = 0 with more unknowns than the dense path takes: ARPACK would stop on a zero
    Krylov vector; the estimate is 0 and the run goes on."""
    n = 300
    T = bigT.from_scipy(sp.diags(np.linspace(1, 2, n)).tocsr(), tmp_path / "T.zarr",
                        tile_size=128, dtype="float64")
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=2, prune=0, progress=False)
    assert rep.spectral_radius == 0 and rep.spectral_uncertainty == 0


def test_a_non_normal_series_that_grows_once_is_not_stopped(tmp_path):
    """rho(M) = 0.447 but ||M|| = 2: the residual of M^(k+1) grows at term 2
    (0.200 -> 0.283) before it falls; the series converges and must run."""
    A = np.array([[1.0, 2.0], [0.1, 1.0]])
    T = bigT.from_scipy(sp.csr_array(A), tmp_path / "T.zarr", tile_size=2, dtype="float64")
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=8, prune=0, progress=False)
    assert rep.terms == 8
    np.testing.assert_allclose(dense(tmp_path / "X.zarr"), dense_stratified(A, 8), rtol=1e-12)
