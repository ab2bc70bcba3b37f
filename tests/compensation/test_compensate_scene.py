"""Compensation on a synthetic corner scene against its ground truth (paper §6.1.3),
and one integration test with the inverse engine."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT import scenes
from bigT.compensation import compensate, fluctuation, relative_error, relight

H, W = 16, 24


def eq13(T, terms):
    """Dense T_n^-1 = F^-1 sum_{k=0..n} (I - T F^-1)^k with F = diag T (paper eq. 13)."""
    F = np.diag(T).copy()
    M = np.eye(len(F)) - T / F[None, :]
    S, P = np.eye(len(F)), np.eye(len(F))
    for _ in range(terms):
        P = M @ P
        S += P
    return S / F[:, None]


def store_like(M, path, T):
    """Store the matrix-ordered dense M with T's tiles and pixel order."""
    po = T.pixel_order
    return bigT.from_scipy(sp.csr_array(M), path, tile_size=T.tile_size, image_shape=po.image_shape,
                           pixel_order=po.order, image_tile=po.image_tile, input_order="matrix",
                           dtype="float64")


@pytest.fixture(scope="module")
def corner(tmp_path_factory):
    d = tmp_path_factory.mktemp("corner")
    scene = scenes.corner(size=(H, W), path=str(d / "T.zarr"))
    # dense references in matrix order, the order of scene.F_stored and of po.to_matrix
    T = scene.T.to_scipy(output_order="matrix").toarray().astype(np.float64)
    A = scene.A.to_scipy(output_order="matrix").toarray().astype(np.float64)
    F = np.asarray(scene.F_stored, dtype=np.float64)
    perm = scene.T.pixel_order.permutation
    # The ground truth F^-1 (I - A), in matrix order (F given in either order).
    cands = [(np.eye(len(F)) - A) / f[:, None] for f in (F, F[perm])]
    resid = [np.abs(x @ T - np.eye(len(F))).max() for x in cands]
    X = cands[int(np.argmin(resid))]
    Xs = store_like(X, d / "X.zarr", scene.T)
    ones = np.ones((H, W))
    c = 0.9 / compensate(Xs, ones, clip=None).max()  # nothing clips above with the exact inverse
    return dict(d=d, scene=scene, T=T, X=X, Xs=Xs, desired=np.full((H, W), c),
                residual=min(resid))


def test_exact_inverse_compensates_corner(corner):
    Ts, T, X, desired = corner["scene"].T, corner["T"], corner["X"], corner["desired"]
    seen0 = relight(Ts, desired)
    l_in, rep = compensate(corner["Xs"], desired, return_report=True)
    seen = relight(Ts, l_in)
    # streamed result = the dense float64 reference
    po = Ts.pixel_order
    ref_in = po.to_images(np.clip(X @ po.to_matrix(desired), 0, 1))
    np.testing.assert_allclose(l_in, ref_in, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(seen, po.to_images(T @ po.to_matrix(ref_in)), rtol=1e-4, atol=1e-6)
    assert relative_error(seen, desired) < 0.1 * relative_error(seen0, desired)
    assert fluctuation(seen) < fluctuation(seen0)
    if corner["residual"] < 1e-5 and rep.clipped_fraction == 0:  # an untruncated scene
        assert relative_error(seen, desired) < 1e-3


def test_four_term_polynomial_beats_uncompensated(corner, capsys):
    Ts, T, desired = corner["scene"].T, corner["T"], corner["desired"]
    seen0 = relight(Ts, desired)
    err0 = relative_error(seen0, desired)
    errs = {}
    for terms in (1, 2, 3, 4):
        Xn = store_like(eq13(T, terms), corner["d"] / f"X{terms}.zarr", Ts)
        l_in = compensate(Xn, desired)
        free = compensate(None, desired, T=Ts, terms=terms, path="matrix-free")
        np.testing.assert_allclose(free, l_in, rtol=1e-4, atol=1e-5)
        seen = relight(Ts, l_in)
        errs[terms] = (relative_error(seen, desired), fluctuation(seen))
    with capsys.disabled():
        print(f"\n[corner {H}x{W}] uncompensated error {err0:.4f} fluct {fluctuation(seen0):.3f}; "
              + "; ".join(f"n={k}: error {e:.4f} fluct {f:.3f}" for k, (e, f) in errs.items()))
    assert errs[4][0] < err0


def test_engine_inverse_matches_matrix_free(tmp_path):
    """Integration: bigT.stratified_inverse without pruning is eq. 13's polynomial."""
    from comp_helpers import make_store, random_transport

    T, _, _, _ = random_transport(10, 12, seed=4)
    Ts = make_store(T, tmp_path / "T.zarr", image_shape=(10, 12), tile_size=48,
                    pixel_order="tile-major")
    bigT.stratified_inverse(Ts, str(tmp_path / "X.zarr"), terms=3, prune=0.0, progress=False)
    X = bigT.open(tmp_path / "X.zarr")
    desired = np.random.default_rng(0).uniform(0.2, 0.6, (3, 10, 12))
    explicit = compensate(X, desired, clip=None)
    free = compensate(None, desired, T=Ts, terms=3, path="matrix-free", clip=None)
    np.testing.assert_allclose(explicit, free, rtol=1e-3, atol=1e-5)
    np.testing.assert_allclose(explicit, (eq13(T, 3) @ desired.reshape(3, -1).T).T.reshape(
        desired.shape), rtol=1e-3, atol=1e-5)
    from bigT.compensation import choose_path

    assert choose_path(X, Ts, None, "auto").cost_matrix_free == 3 * Ts.nnz  # terms from X
