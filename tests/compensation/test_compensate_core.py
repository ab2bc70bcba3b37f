"""compensate / relight / matrix-free / bounces against dense numpy references."""

from __future__ import annotations

import numpy as np
import pytest

import bigT
from bigT.compensation import (choose_path, compensate, matrix_free_apply, relight,
                               separate_bounces, stream_matmul)
from bigT.errors import ImageError

from comp_helpers import make_store, random_transport


def rowmajor(images):
    images = np.asarray(images)
    return images.reshape(images.shape[0], -1).T if images.ndim == 3 else images.ravel()


def test_public_names():
    assert bigT.compensate is compensate
    assert bigT.relight is relight
    assert bigT.separate_bounces is separate_bounces


def test_exact_inverse_gives_desired(small_scene, tmp_path):
    s = small_scene
    H, W = s["H"], s["W"]
    X = make_store(s["X"], tmp_path / "X.zarr", image_shape=(H, W), tile_size=32)
    T = make_store(s["T"], tmp_path / "T.zarr", image_shape=(H, W), tile_size=32)
    # A smooth target whose exact pre-image stays inside [0, 1]: X d with d in [0.3, 0.5].
    yy, xx = np.mgrid[0:H, 0:W]
    desired = 0.3 + 0.2 * (xx / W) * (yy / H)
    pre = (s["X"] @ desired.ravel())
    assert pre.min() > 0 and pre.max() < 1, "target chosen so that nothing clips"
    l_in, report = compensate(X, desired, return_report=True)
    assert l_in.shape == desired.shape
    assert report.clipped_fraction == 0
    np.testing.assert_allclose(l_in.ravel(), pre, rtol=1e-5, atol=1e-6)
    seen = relight(T, l_in)
    np.testing.assert_allclose(seen, desired, rtol=1e-4, atol=1e-5)


def test_clipping_counts_and_bounds(small_scene, tmp_path):
    s = small_scene
    X = make_store(s["X"], tmp_path / "X.zarr", image_shape=(s["H"], s["W"]), tile_size=32)
    rng = np.random.default_rng(1)
    desired = rng.uniform(0, 1, (3, s["H"], s["W"]))
    l_in, report = compensate(X, desired, clip=(0, 1), batch=2, return_report=True)
    raw = (s["X"] @ rowmajor(desired)).T.reshape(desired.shape)
    np.testing.assert_allclose(l_in, np.clip(raw, 0, 1), rtol=1e-5, atol=1e-6)
    expected = np.count_nonzero((raw < 0) | (raw > 1)) / raw.size
    assert report.clipped_fraction == pytest.approx(expected)
    assert report.clipped_fraction > 0
    unclipped = compensate(X, desired, clip=None)
    np.testing.assert_allclose(unclipped, raw, rtol=1e-5, atol=1e-6)


_STREAM_STORES = {}


@pytest.fixture(scope="module")
def stream_stores(tmp_path_factory):
    """(tile_size, order) -> (T, X, T store, X store), written once per module."""
    def get(tile_size, order):
        key = (tile_size, order)
        if key not in _STREAM_STORES:
            d = tmp_path_factory.mktemp(f"s{tile_size}{order}")
            T, X, _, _ = random_transport(10, 12, seed=tile_size)
            _STREAM_STORES[key] = (T, X, make_store(T, d / "T.zarr", image_shape=(10, 12),
                                                    tile_size=tile_size, pixel_order=order),
                                   make_store(X, d / "X.zarr", image_shape=(10, 12),
                                              tile_size=tile_size, pixel_order=order))
        return _STREAM_STORES[key]
    return get


@pytest.mark.parametrize("batch", [1, 3, 64])
@pytest.mark.parametrize("tile_size,order", [(120, "row-major"), (37, "row-major"),
                                              (29, "tile-major")])
def test_streamed_equals_scipy(batch, tile_size, order, stream_stores):
    H, W = 10, 12
    T, X, Ts, Xs = stream_stores(tile_size, order)
    rng = np.random.default_rng(batch)
    desired = rng.uniform(0, 1, (5, H, W))
    got = compensate(Xs, desired, clip=None, batch=batch)
    ref = (X.astype(np.float32).astype(np.float64) @ rowmajor(desired)).T.reshape(desired.shape)
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-5)
    seen = relight(Ts, desired, batch=batch)
    np.testing.assert_allclose(seen, (T @ rowmajor(desired)).T.reshape(desired.shape),
                               rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("budget", [0, 3000, 1 << 30])
def test_tile_cache_same_result_bounded(tmp_path, budget):
    from bigT.schedule.worker import STATE

    T, X, F, A = random_transport(10, 12, seed=9)
    Xs = make_store(X, tmp_path / "X.zarr", image_shape=(10, 12), tile_size=32)
    V = np.random.default_rng(0).uniform(size=(120, 4))
    cache = STATE.cache  # the process's tile cache, the engine's too
    cache.drop_where(lambda path: True)
    cache.resize(1 << 20)
    other = str(tmp_path)  # an existing path: entries of vanished stores are dropped
    cache.get((other, "row", 0), lambda: np.zeros(8))  # someone else's entry
    cache.hits = cache.misses = 0
    first = stream_matmul(Xs, V, cache_bytes=budget)
    second = stream_matmul(Xs, V, cache_bytes=budget)
    np.testing.assert_array_equal(first, second)
    np.testing.assert_allclose(first, X.astype(np.float32) @ V, rtol=1e-5, atol=1e-6)
    # the cache holds what a mat-vec reads at once: a tile row (format 2 stores rows whole)
    n_tiles = Xs.grid[0] if Xs.row_layout else int(Xs.tile_nnz.size)
    if budget == 0:  # nothing cached, and the cache is left as it was
        assert (cache.hits, cache.misses) == (0, 0)
        assert cache.lookup((other, "row", 0)) is not None
        return
    assert cache.used <= budget
    assert cache.hits + cache.misses == 2 * n_tiles
    assert (cache.hits == n_tiles) == (budget == 1 << 30)
    assert (cache.hits == 0) == (budget == 0)


def test_pixel_order_round_trip(tmp_path):
    """A tile-major store takes and returns row-major images (non-symmetric matrix)."""
    H, W = 9, 13  # ragged image tiles
    rng = np.random.default_rng(3)
    M = rng.uniform(0, 1, (H * W, H * W)) * (rng.uniform(size=(H * W, H * W)) < 0.1)
    store = make_store(M, tmp_path / "M.zarr", image_shape=(H, W), tile_size=40,
                       pixel_order="tile-major")
    assert store.pixel_order.order == "tile-major"
    img = rng.uniform(0, 1, (H, W))
    out = relight(store, img)
    np.testing.assert_allclose(out, (M @ img.ravel()).reshape(H, W), rtol=1e-5, atol=1e-5)
    # the raw streamed product is in matrix order, not row-major
    v = store.pixel_order.to_matrix(img)
    raw = stream_matmul(store, v)
    np.testing.assert_allclose(store.pixel_order.to_images(raw), out, rtol=1e-5, atol=1e-5)


def eq13(T, F, terms):
    """Dense T_n^-1 = F^-1 sum_{k=0..n} (I - T F^-1)^k (paper eq. 13)."""
    n = T.shape[0]
    M = np.eye(n) - T / F[None, :]
    S, P = np.eye(n), np.eye(n)
    for _ in range(terms):
        P = M @ P
        S = S + P
    return S / F[:, None]


@pytest.mark.parametrize("terms", [0, 1, 2, 4])
def test_matrix_free_equals_explicit(small_scene, tmp_path, terms):
    s = small_scene
    H, W = s["H"], s["W"]
    T = s["T"]
    d = np.diag(T).copy()
    Xn = eq13(T, d, terms)
    Ts = make_store(T, tmp_path / "T.zarr", image_shape=(H, W), tile_size=50,
                    pixel_order="tile-major")
    Xs = make_store(Xn, tmp_path / "X.zarr", image_shape=(H, W), tile_size=50)
    desired = np.random.default_rng(terms).uniform(0.2, 0.8, (4, H, W))
    explicit = compensate(Xs, desired, clip=None, batch=3)
    free, rep = compensate(None, desired, clip=None, T=Ts, terms=terms, path="matrix-free",
                           return_report=True, batch=3)
    assert rep.choice.path == "matrix-free"
    np.testing.assert_allclose(free, explicit, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(free, (Xn @ rowmajor(desired)).T.reshape(desired.shape),
                               rtol=1e-4, atol=1e-5)


def test_matrix_free_apply_in_matrix_order(small_scene, tmp_path):
    s = small_scene
    Ts = make_store(s["T"], tmp_path / "T.zarr", image_shape=(s["H"], s["W"]), tile_size=64)
    b = np.random.default_rng(0).uniform(size=(s["H"] * s["W"], 2))
    y = matrix_free_apply(Ts, b, 3)
    ref = eq13(s["T"], np.diag(s["T"]).copy(), 3) @ b
    np.testing.assert_allclose(y, ref, rtol=1e-4, atol=1e-5)


def test_choose_path_cost_model(small_scene, tmp_path):
    s = small_scene
    shape = (s["H"], s["W"])
    Tsparse = np.where(np.abs(s["T"]) > 0.01, s["T"], 0)
    T = make_store(Tsparse, tmp_path / "T.zarr", image_shape=shape)
    X = make_store(s["X"], tmp_path / "X.zarr", image_shape=shape)
    for terms in (1, 50):
        c = choose_path(X, T, terms, "auto")
        cheaper = "explicit" if X.nnz <= terms * T.nnz else "matrix-free"
        assert c.path == cheaper
        assert "cheaper" in c.reason
    assert choose_path(X, None, 4, "auto").path == "explicit"
    assert choose_path(None, T, 4, "auto").path == "matrix-free"
    assert choose_path(X, T, 4, "explicit").path == "explicit"


@pytest.mark.parametrize("bounces", [0, 1, 4])
def test_bounces_sum_to_T_l(small_scene, tmp_path, bounces):
    s = small_scene
    H, W = s["H"], s["W"]
    T = make_store(s["T"], tmp_path / "T.zarr", image_shape=(H, W), tile_size=50,
                   pixel_order="tile-major")
    X = make_store(s["X"], tmp_path / "X.zarr", image_shape=(H, W), tile_size=50)
    l = np.random.default_rng(5).uniform(0, 1, (H, W))
    parts = separate_bounces(T, X, l, bounces)
    assert parts.shape == (bounces + 2, H, W)
    Tl = (s["T"] @ l.ravel()).reshape(H, W)
    np.testing.assert_allclose(parts.sum(axis=0), Tl, rtol=1e-4, atol=1e-5)
    # with the exact inverse, b_k = A^k F l and F is recovered exactly (eq. 33)
    v = s["F"] * l.ravel()
    for k in range(bounces + 1):
        np.testing.assert_allclose(parts[k].ravel(), v, rtol=1e-3, atol=1e-5)
        v = s["A"] @ v
    # the remainder is the tail sum_{k>K} A^k F l = T l - sum_{k<=K} A^k F l
    tail, v = Tl.ravel().copy(), s["F"] * l.ravel()
    for k in range(bounces + 1):
        tail -= v
        v = s["A"] @ v
    np.testing.assert_allclose(parts[-1].ravel(), tail, atol=1e-4)
    assert np.abs(tail).max() > 1e-3  # a real remainder, not a trivially zero one


def test_bad_image_shape_is_image_error(small_scene, tmp_path):
    s = small_scene
    X = make_store(s["X"], tmp_path / "X.zarr", image_shape=(s["H"], s["W"]))
    with pytest.raises(ImageError, match=r"\(11, 12\).*\(10, 12\)"):
        compensate(X, np.zeros((11, 12)))
    with pytest.raises(ImageError, match="NaN"):
        compensate(X, np.full((s["H"], s["W"]), np.nan))


@pytest.mark.parametrize("limit", [-1, 10**18], ids=["numba", "numpy"])
@pytest.mark.parametrize("order", ["row-major", "tile-major"])
def test_pixel_kernels_match_pixel_order(order, limit, monkeypatch):
    from bigT import config
    from bigT.storage.frames import frames_to_matrix, matrix_to_frames

    monkeypatch.setattr(config, "KERNEL_NUMPY_MAX_WORK", limit)
    from bigT.storage.pixel_order import PixelOrder

    po = PixelOrder((13, 21), order, (8, 8))  # ragged image tiles
    frames = np.random.default_rng(0).uniform(-0.5, 1.5, (5, 13, 21))
    B = frames_to_matrix(frames, po, np.float64)
    np.testing.assert_array_equal(B, po.to_matrix(frames))
    back, below, above = matrix_to_frames(B, po, (0.0, 1.0))
    np.testing.assert_array_equal(back, np.clip(frames, 0, 1))
    assert (below, above) == (np.count_nonzero(frames < 0), np.count_nonzero(frames > 1))
    raw, below, above = matrix_to_frames(B, po, (0.0, None))
    np.testing.assert_array_equal(raw, np.maximum(frames, 0))
    assert above == 0
    np.testing.assert_array_equal(matrix_to_frames(B, po, None)[0], po.to_images(B))
