"""One convention per vector (issue 27, point 7): a BlockCSR's public products and
exports speak row-major image vectors (``image.ravel()``), whatever pixel order the
store keeps inside; the stored order is there only when asked for by name.

The references are independent of the permutation code under test: the same scene
built in row-major order (its stored matrix *is* the row-major T), ``bigT.relight``
(the streamed engine product and the frame helpers) and the ``.npz`` that ``bigT
export`` writes, read back with scipy.
"""

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT.cli import main
from bigT.storage import from_scipy
from bigT.storage.convert import load_matrix

SIZE = (16, 24)   # 2 x 3 image tiles of 8 x 8: tile-major differs from row-major
TILE = 64         # 6 x 6 matrix tiles


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """The corner at SIZE stored tile-major (the default) and row-major, float64."""
    root = tmp_path_factory.mktemp("vector-order")
    kw = {"tile_size": TILE, "dtype": "float64", "preview": False, "progress": False}
    tiled = bigT.scenes.corner(size=SIZE, path=root / "tiled.zarr", pixel_order="tile-major", **kw)
    plain = bigT.scenes.corner(size=SIZE, path=root / "plain.zarr", pixel_order="row-major", **kw)
    return tiled, plain


@pytest.fixture(scope="module")
def images():
    """(3, H, W): the unit image of the issue and two that are not symmetric."""
    rng = np.random.default_rng(27)
    return np.stack([np.ones(SIZE), rng.random(SIZE), np.linspace(0, 1, SIZE[0] * SIZE[1]).reshape(SIZE)])


def test_the_stores_really_differ_in_their_stored_order(scenes):
    tiled, plain = scenes
    assert tiled.T.pixel_order.order == "tile-major" and plain.T.pixel_order.order == "row-major"
    # the same transport, numbered differently inside: otherwise this file tests nothing
    assert (tiled.T.to_scipy(output_order="matrix") != plain.T.to_scipy(output_order="matrix")).nnz > 0


def test_a_times_an_image_vector_is_relight(scenes, images):
    """The issue's example: ``T @ img.ravel()`` is what the camera sees, as relight says."""
    tiled, plain = scenes
    T = tiled.T
    row_major_T = plain.T.to_scipy(output_order="matrix")  # stored row-major: no permutation
    for img in images:
        x = img.ravel()
        seen = bigT.relight(T, img).ravel()
        np.testing.assert_allclose(T @ x, seen, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(T.matmul(x), seen, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(T @ x, row_major_T @ x, rtol=1e-10, atol=1e-12)


def test_a_batch_of_image_vectors_is_a_batch_of_relit_images(scenes, images):
    T = scenes[0].T
    K = len(images)
    X = images.reshape(K, -1).T  # (n, K) columns of image.ravel()
    Y = T @ X
    assert Y.shape == (T.shape[0], K)
    np.testing.assert_allclose(Y.T.reshape(images.shape), bigT.relight(T, images),
                               rtol=1e-10, atol=1e-12)


def test_the_stored_order_gives_the_old_numbers_when_asked_for(scenes, images):
    T = scenes[0].T
    po = T.pixel_order
    for img in images:
        seen = bigT.relight(T, img)
        inside = T.matmul(po.to_matrix(img), order="matrix")  # matrix-ordered in and out
        np.testing.assert_allclose(po.to_images(inside), seen, rtol=1e-10, atol=1e-12)
    # a row-major vector read as matrix-ordered is the silent error the issue found
    unit = images[0].ravel()
    wrong = T.matmul(unit, order="matrix")
    assert np.abs(wrong - bigT.relight(T, images[0]).ravel()).max() > 0.1


def test_to_scipy_is_what_bigT_export_writes(scenes, tmp_path, images):
    tiled, plain = scenes
    T = tiled.T
    assert main(["export", str(T.path), "-o", str(tmp_path / "T.npz")]) == 0
    exported = sp.csr_array(load_matrix(tmp_path / "T.npz"))
    A = T.to_scipy()
    assert A.has_sorted_indices and A.shape == exported.shape
    assert (A != exported).nnz == 0
    np.testing.assert_allclose(A.toarray(), plain.T.to_scipy(output_order="matrix").toarray(),
                               rtol=1e-10, atol=1e-12)
    x = images[1].ravel()
    np.testing.assert_allclose(exported @ x, T @ x, rtol=1e-10, atol=1e-12)


def test_to_scipy_in_matrix_order_is_the_stored_tiles(scenes):
    T = scenes[0].T
    stored = sp.vstack([T.get_tile_row(i) for i in range(T.grid[0])], format="csr")
    assert (T.to_scipy(output_order="matrix") != stored).nnz == 0
    perm = T.pixel_order.permutation  # matrix index k is row-major pixel perm[k]
    assert (T.to_scipy()[perm][:, perm] != stored).nnz == 0


def test_diagonal_follows_to_scipy_in_either_order(scenes):
    tiled, plain = scenes
    T = tiled.T
    np.testing.assert_array_equal(T.diagonal(), T.to_scipy().diagonal())
    np.testing.assert_array_equal(T.diagonal(output_order="matrix"),
                                  T.to_scipy(output_order="matrix").diagonal())
    np.testing.assert_allclose(T.diagonal(), plain.T.diagonal(output_order="matrix"),
                               rtol=1e-10, atol=1e-12)
    # the scene's first bounce F is kept in matrix order, the engine's: there T = (I - A)^-1 F
    # with A >= 0 gives T_ii >= F_ii, and close (little light comes back to its own pixel)
    ratio = T.diagonal(output_order="matrix") / tiled.F_stored
    assert ratio.min() >= 1.0 and ratio.max() < 1.05


def test_without_a_pixel_order_both_orders_are_the_one_order(tmp_path):
    A = sp.csr_array(sp.random(30, 30, density=0.2, format="csr", random_state=1))
    S = from_scipy(A, tmp_path / "a.zarr", tile_size=8, dtype="float64")
    x = np.random.default_rng(0).random(30)
    assert S.pixel_order is None
    np.testing.assert_allclose(S @ x, A @ x, rtol=1e-12)
    np.testing.assert_array_equal(S.matmul(x, order="matrix"), S @ x)
    assert (S.to_scipy(output_order="matrix") != S.to_scipy()).nnz == 0
    np.testing.assert_array_equal(S.diagonal(output_order="matrix"), S.diagonal())


@pytest.mark.parametrize("call", [
    lambda S: S.matmul(np.ones(S.shape[1]), order="tile-major"),
    lambda S: S.to_scipy(output_order="tile-major"),
    lambda S: S.diagonal(output_order="col-major"),
])
def test_an_unknown_order_is_refused_naming_the_argument(scenes, call):
    with pytest.raises(ValueError, match=r"order must be one of \('row-major', 'matrix'\)"):
        call(scenes[0].T)
