"""The colour store (docs/FORMAT.md, "Colour"): index 3 p + c, channels in the
attributes, tile sizes a multiple of 3, convert/export round trips."""

import json

import numpy as np
import pytest
import scipy.sparse as sp

from bigT.cli import main
from bigT.errors import CorruptStoreError, ImageError, ShapeMismatchError
from bigT.storage import open as open_store
from bigT.storage.frames import as_frames, to_frames, to_vectors
from bigT.storage.pixel_order import PixelOrder
from bigT.storage.writer import from_scipy

H, W = 4, 6


def _colour_matrix(n_pixels, seed=0):
    rng = np.random.default_rng(seed)
    A = sp.random(3 * n_pixels, 3 * n_pixels, density=0.15, random_state=rng, format="csr")
    return sp.csr_array(A + sp.eye(3 * n_pixels))


def test_colour_permutation_keeps_channels_adjacent():
    grey = PixelOrder((H, W), "tile-major", (2, 4))
    colour = PixelOrder((H, W), "tile-major", (2, 4), channels=3)
    assert colour.n == 3 * grey.n and colour.pixels == grey.n
    assert colour.frame_shape == (H, W, 3)
    # value 3 p + c of the matrix is channel c of row-major pixel perm[p]: an explicit loop
    expected = [3 * grey.permutation[p] + c for p in range(grey.n) for c in range(3)]
    np.testing.assert_array_equal(colour.permutation, expected)


def test_colour_images_round_trip_through_matrix_order():
    order = PixelOrder((H, W), "tile-major", (2, 2), channels=3)
    images = np.random.default_rng(1).random((5, H, W, 3))
    V = to_vectors(images, order, np.float64)
    assert V.shape == (3 * H * W, 5)
    # row-major numbering of an (H, W, 3) image is its ravel: index 3 (y W + x) + c
    np.testing.assert_array_equal(V[:, 2], images[2].ravel()[order.permutation])
    np.testing.assert_array_equal(to_frames(V, order), images)


def test_store_product_matches_scipy_in_row_major_image_order(tmp_path):
    A = _colour_matrix(H * W)
    T = from_scipy(A, tmp_path / "T.zarr", image_shape=(H, W), pixel_order="tile-major",
                   image_tile=(2, 2), channels=3, tile_size=9)
    assert T.channels == 3 and T.tile_size == 9
    x = np.random.default_rng(2).random((H, W, 3))
    np.testing.assert_allclose(T @ x.ravel(), A @ x.ravel(), rtol=1e-6)
    assert abs(T.to_scipy() - A).max() < 1e-6
    attrs = json.loads((tmp_path / "T.zarr" / "zarr.json").read_text())["attributes"]["bigT"]
    assert attrs["channels"] == 3


def test_grey_store_attributes_have_no_channels_key(tmp_path):
    T = from_scipy(sp.eye(H * W, format="csr"), tmp_path / "G.zarr", image_shape=(H, W))
    assert T.channels == 1
    attrs = json.loads((tmp_path / "G.zarr" / "zarr.json").read_text())["attributes"]["bigT"]
    assert "channels" not in attrs


def test_default_colour_tile_size_is_a_multiple_of_three(tmp_path):
    T = from_scipy(_colour_matrix(H * W), tmp_path / "T.zarr", image_shape=(H, W), channels=3)
    assert T.tile_size % 3 == 0


@pytest.mark.parametrize("kwargs, words", [
    ({"image_shape": (H, W), "channels": 3, "tile_size": 8}, "not a multiple of 3"),
    ({"channels": 3}, "needs image_shape"),
    ({"image_shape": (H, W), "channels": 2}, "channels must be 1"),
])
def test_bad_colour_layouts_are_refused(tmp_path, kwargs, words):
    with pytest.raises(ShapeMismatchError, match=words):
        from_scipy(_colour_matrix(H * W), tmp_path / "T.zarr", **kwargs)


def test_reader_refuses_colour_store_with_straddling_tiles(tmp_path):
    from_scipy(_colour_matrix(H * W), tmp_path / "T.zarr", image_shape=(H, W), channels=3,
               tile_size=9)
    meta_path = tmp_path / "T.zarr" / "zarr.json"
    meta = json.loads(meta_path.read_text())
    meta["attributes"]["bigT"]["tile_size"] = 8
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(CorruptStoreError, match="multiple"):
        open_store(tmp_path / "T.zarr")


@pytest.mark.parametrize("change", [{"channels": 2}, {"channels": True}, {"channels": "3"},
                                    {"image_shape": None}])
def test_reader_refuses_bad_channel_attributes(tmp_path, change):
    from_scipy(_colour_matrix(H * W), tmp_path / "T.zarr", image_shape=(H, W), channels=3,
               tile_size=9)
    meta_path = tmp_path / "T.zarr" / "zarr.json"
    meta = json.loads(meta_path.read_text())
    meta["attributes"]["bigT"].update(change)
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(CorruptStoreError):
        open_store(tmp_path / "T.zarr")


def test_images_of_the_wrong_kind_are_refused_in_one_line(tmp_path):
    colour = from_scipy(_colour_matrix(H * W), tmp_path / "C.zarr", image_shape=(H, W),
                        channels=3, tile_size=9)
    grey = from_scipy(sp.eye(H * W, format="csr"), tmp_path / "G.zarr", image_shape=(H, W))
    for images in (np.zeros((H, W)), np.zeros((2, H, W))):
        with pytest.raises(ImageError, match="grey images .* colour transport"):
            as_frames(images, colour)
    for images in (np.zeros((H, W, 3)), np.zeros((2, H, W, 3))):
        with pytest.raises(ImageError, match="colour images .* grey transport"):
            as_frames(images, grey)


def test_convert_and_export_round_trip_on_the_command_line(tmp_path, capsys):
    A = _colour_matrix(H * W)
    sp.save_npz(tmp_path / "T.npz", sp.csr_matrix(A))
    assert main(["convert", str(tmp_path / "T.npz"), "-o", str(tmp_path / "T.zarr"),
                 "--image-shape", f"{H}x{W}", "--channels", "3",
                 "--pixel-order", "tile-major", "--tile-size", "12"]) == 0
    capsys.readouterr()
    assert main(["info", str(tmp_path / "T.zarr")]) == 0
    assert "colour (3 channels" in capsys.readouterr().out
    assert main(["export", str(tmp_path / "T.zarr"), "-o", str(tmp_path / "back.npz")]) == 0
    back = sp.load_npz(tmp_path / "back.npz")
    assert abs(back - A).max() < 1e-6


LEFT = np.array([[1.2, -0.1, 0.05], [-0.2, 1.1, -0.1], [0.0, -0.15, 1.3]])
RIGHT = np.array([[0.9, 0.2, -0.05], [0.1, 1.05, 0.0], [-0.1, 0.05, 0.8]])


def _factored_store(path, S, **kwargs):
    """A colour store of the tiles ``S`` with the attribute mixing {LEFT, RIGHT} set."""
    from_scipy(S, path, image_shape=(H, W), channels=3, dtype="float64", **kwargs)
    meta_path = path / "zarr.json"
    meta = json.loads(meta_path.read_text())
    meta["attributes"]["bigT"]["mixing"] = {"left": LEFT.tolist(), "right": RIGHT.tolist()}
    meta_path.write_text(json.dumps(meta))
    return open_store(path)


@pytest.mark.parametrize("layout", [{"tile_size": 9},
                                    {"tile_size": 12, "pixel_order": "tile-major",
                                     "image_tile": (2, 3)}])
def test_a_factored_store_represents_L_S_R_in_every_product(tmp_path, layout):
    """matmul, @, to_scipy (both orders), diagonal and represented_rows are of the dense
    (I (x) L) S (I (x) R); the tiles and rows stay S."""
    S = _colour_matrix(H * W, seed=3)  # row-major, as given to from_scipy
    A = _factored_store(tmp_path / "T.zarr", S, **layout)
    n = H * W
    dense = np.kron(np.eye(n), LEFT) @ S.toarray() @ np.kron(np.eye(n), RIGHT)
    assert A.mixing is not None and A.nnz == S.nnz
    np.testing.assert_allclose(A.mixing.left, LEFT)
    np.testing.assert_allclose(A.to_scipy().toarray(), dense, atol=1e-14)
    x = np.random.default_rng(4).random((3 * n, 5))
    np.testing.assert_allclose(A.matmul(x), dense @ x, atol=1e-13)
    np.testing.assert_allclose(A @ x[:, 0], dense @ x[:, 0], atol=1e-13)
    np.testing.assert_allclose(A.diagonal(), np.diag(dense), atol=1e-14)
    perm = A.pixel_order.permutation  # matrix index -> row-major value
    stored = dense[np.ix_(perm, perm)]
    np.testing.assert_allclose(A.to_scipy(output_order="matrix").toarray(), stored, atol=1e-14)
    np.testing.assert_allclose(A.matmul(x, order="matrix"), stored @ x, atol=1e-13)
    np.testing.assert_allclose(A.diagonal(output_order="matrix"), np.diag(stored), atol=1e-14)
    np.testing.assert_allclose(A.represented_rows(6, 18).toarray(), stored[6:18], atol=1e-14)
    np.testing.assert_allclose(A.get_rows(0, 3 * n).toarray(),
                               S.toarray()[np.ix_(perm, perm)])  # raw rows: S


@pytest.mark.parametrize("mixing, words", [
    ({"left": np.eye(3).tolist()}, "left and right"),
    ({"left": np.eye(2).tolist(), "right": np.eye(3).tolist()}, "3x3"),
    ({"left": [[1, 0, 0], [0, 1, 0], [0, 0, None]], "right": np.eye(3).tolist()}, "finite"),
    ("identity", "left and right")])
def test_reader_refuses_a_bad_mixing_attribute_in_one_line(tmp_path, mixing, words):
    from_scipy(_colour_matrix(H * W), tmp_path / "T.zarr", image_shape=(H, W), channels=3,
               tile_size=9)
    meta_path = tmp_path / "T.zarr" / "zarr.json"
    meta = json.loads(meta_path.read_text())
    meta["attributes"]["bigT"]["mixing"] = mixing
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(CorruptStoreError, match=f"bad mixing attribute.*{words}") as err:
        open_store(tmp_path / "T.zarr")
    assert "\n" not in str(err.value)


def test_reader_refuses_mixing_on_a_grey_store(tmp_path):
    from_scipy(sp.eye(12, format="csr"), tmp_path / "T.zarr", image_shape=(3, 4))
    meta_path = tmp_path / "T.zarr" / "zarr.json"
    meta = json.loads(meta_path.read_text())
    meta["attributes"]["bigT"]["mixing"] = {"left": np.eye(3).tolist(),
                                            "right": np.eye(3).tolist()}
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(CorruptStoreError, match="mixing without channels 3"):
        open_store(tmp_path / "T.zarr")
