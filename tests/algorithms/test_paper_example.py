"""Paper §5.1: the 4x4 dihedral of eq. 34, term by term against a dense numpy
evaluation of eq. 13, and the first bounce recovered by eq. 42.

The printed eqs. 35-41 are NOT consistent with the printed T of eq. 34 (eq. 37's
diagonal is not the inverse of eq. 36's; eq. 38 is not symmetric where T is), so the
references here are computed independently from eq. 34 (conftest.dense_stratified),
and the only printed numbers used are the true F = 1.750 and eq. 43's 1.7498.
"""

import numpy as np
import pytest

import bigT
from bigT.algorithms import recover_first_bounce

from inverse_helpers import T_PAPER, dense, dense_stratified


@pytest.mark.parametrize("terms", [0, 1, 2, 3, 4])
def test_power_term_by_term(tmp_path, make_store, terms):
    T = make_store(T_PAPER, tile_size=2)
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=terms, prune=0, progress=False)
    assert rep.terms == terms
    assert [h.term for h in rep.history] == list(range(terms + 1))
    np.testing.assert_allclose(dense(tmp_path / "X.zarr"), dense_stratified(T_PAPER, terms),
                               rtol=0, atol=1e-12)


def test_recovered_first_bounce_is_1750(tmp_path, make_store):
    T = make_store(T_PAPER, tile_size=2)
    bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=8, prune=0, progress=False)
    f = recover_first_bounce(tmp_path / "X.zarr")
    # true F is 1.750 (paper §5.1); eq. 43 prints 1.7498 at T_4^-1
    np.testing.assert_allclose(np.round(f, 3), 1.750)


def test_recovered_first_bounce_at_four_terms_is_close_to_eq43(tmp_path, make_store):
    T = make_store(T_PAPER, tile_size=2)
    bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=4, prune=0, progress=False)
    f = recover_first_bounce(bigT.open(tmp_path / "X.zarr"))
    np.testing.assert_allclose(f, 1.7498, atol=5e-4)
    np.testing.assert_allclose(f, 1.0 / np.diag(dense_stratified(T_PAPER, 4)), rtol=1e-12)


def test_second_run_with_recovered_first_bounce(tmp_path, make_store):
    T = make_store(T_PAPER, tile_size=2)
    bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=8, prune=0, progress=False)
    f = recover_first_bounce(tmp_path / "X.zarr")
    np.save(tmp_path / "F.npy", f)
    rep = bigT.stratified_inverse(T, tmp_path / "X2.zarr", terms=4, prune=0, progress=False,
                                  first_bounce=str(tmp_path / "F.npy"))
    assert rep.first_bounce == "vector"
    np.testing.assert_allclose(dense(tmp_path / "X2.zarr"), dense_stratified(T_PAPER, 4, f),
                               atol=1e-12)


def test_identity_first_bounce_diverges(tmp_path, make_store):
    T = make_store(T_PAPER, tile_size=2)
    rho = max(abs(np.linalg.eigvals(np.eye(4) - T_PAPER)))
    assert rho >= 1  # the paper's Fig. 5: F = I is not guaranteed to work
    with pytest.raises(bigT.DivergenceError, match=rf"spectral radius .* is {rho:.4f} \+- "):
        bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=4, first_bounce="identity",
                                progress=False)
    rep = bigT.stratified_inverse(T, tmp_path / "Y.zarr", terms=2, first_bounce="identity",
                                  prune=0, progress=False, force=True)
    assert rep.spectral_radius == pytest.approx(rho, rel=1e-12)  # all eigenvalues, 4x4
    np.testing.assert_allclose(dense(tmp_path / "Y.zarr"),
                               dense_stratified(T_PAPER, 2, np.ones(4)), atol=1e-12)
