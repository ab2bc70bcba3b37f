"""Zero/negative diagonals and unreachable pixels; recover_first_bounce."""

import numpy as np
import pytest

import bigT
from bigT.algorithms import recover_first_bounce

from inverse_helpers import dense, dense_stratified, random_dominant


def test_unreachable_pixels_are_left_out(tmp_path, make_store):
    A = random_dominant(40, seed=1)
    dark = [3, 17, 30]
    A[dark, :] = 0
    A[:, dark] = 0
    T = make_store(A)
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=3, prune=0, progress=False)
    assert rep.excluded_pixels == 3
    X = dense(tmp_path / "X.zarr")
    assert not X[dark].any() and not X[:, dark].any()
    keep = np.setdiff1d(np.arange(40), dark)
    np.testing.assert_allclose(X[np.ix_(keep, keep)],
                               dense_stratified(A[np.ix_(keep, keep)], 3), atol=1e-12)
    f = recover_first_bounce(X)
    assert (f[dark] == 0).all() and (f[keep] > 0).all()


def test_zero_diagonal_on_lit_pixel(tmp_path, make_store):
    A = random_dominant(40, seed=2)
    A[5, 5] = 0
    A[5, 6] = 0.1
    A[9, 9] = 0
    T = make_store(A)
    with pytest.raises(bigT.InvalidMatrixError, match=r"2 zero entries .*first at index 5"):
        bigT.stratified_inverse(T, tmp_path / "X.zarr", progress=False)


def test_negative_diagonal(tmp_path, make_store):
    A = random_dominant(40, seed=3)
    A[12, 12] = -1
    T = make_store(A)
    with pytest.raises(bigT.InvalidMatrixError, match=r"1 negative entries \(first at index 12"):
        bigT.stratified_inverse(T, tmp_path / "X.zarr", progress=False)


def test_recover_first_bounce_inputs():
    X = np.diag([2.0, 0.5, 0.0])
    np.testing.assert_array_equal(recover_first_bounce(X), [0.5, 2.0, 0.0])
    import scipy.sparse as sp

    np.testing.assert_array_equal(recover_first_bounce(sp.csr_array(X)), [0.5, 2.0, 0.0])


def test_first_bounce_vector_shape(tmp_path, make_store):
    T = make_store(random_dominant(20, seed=4))
    with pytest.raises(bigT.ShapeMismatchError):
        bigT.stratified_inverse(T, tmp_path / "X.zarr", first_bounce=np.ones(5), progress=False)


def test_first_bounce_vectors_are_row_major_images(tmp_path):
    """recover_first_bounce gives F as an image (row-major) on a tile-major scene, and a
    first_bounce= vector is read the same way: the round trip of eq. 33 lands on the
    scene's true F, which the scene keeps in its stored order."""
    scene = bigT.scenes.corner(size=(16, 24), path=tmp_path / "T.zarr", preview=False,
                               progress=False, pixel_order="tile-major", dtype="float64")
    order = scene.pixel_order
    assert not np.array_equal(order.permutation, np.arange(order.n))  # a real reordering
    X = tmp_path / "X.zarr"
    bigT.stratified_inverse(scene.T, X, terms=60, prune=0, progress=False)
    F_image = recover_first_bounce(X)                      # what a user saves as F.npy
    F_stored = recover_first_bounce(X, output_order="matrix")
    np.testing.assert_allclose(F_stored, scene.F_stored, rtol=1e-6)   # eq. 33
    np.testing.assert_allclose(F_image, scene.F, rtol=1e-6)          # as an image
    np.testing.assert_allclose(scene.F, order.to_images(scene.F_stored).ravel())
    np.save(tmp_path / "F.npy", F_image)
    second = bigT.stratified_inverse(scene.T, tmp_path / "X2.zarr", terms=1, prune=0,
                                     first_bounce=str(tmp_path / "F.npy"), progress=False)
    assert second.first_bounce == "vector"
    fb = bigT.algorithms.resolve_first_bounce(scene.T, scene.F)   # first_bounce=scene.F
    np.testing.assert_allclose(fb.f, scene.F_stored, rtol=1e-12)  # back in the stored order


def test_errors_name_the_pixel_a_user_sees(tmp_path):
    """On a tile-major store, a bad first_bounce entry is named by its image pixel
    (y, x), not by its row in the stored order."""
    scene = bigT.scenes.corner(size=(16, 24), path=tmp_path / "T.zarr", preview=False,
                               progress=False, pixel_order="tile-major")
    F = scene.F.copy()
    F[3 * 24 + 17] = -1.0  # pixel (3, 17) of the row-major image vector
    with pytest.raises(bigT.InvalidMatrixError, match=r"first at pixel \(3, 17\)"):
        bigT.algorithms.resolve_first_bounce(scene.T, F)
