"""Round trips of the block-CSR store against scipy (the independent reference)."""

import os
import tempfile

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings, strategies as st

from bigT import config
from bigT.errors import MemoryLimitError, ShapeMismatchError, StoreError, IncompleteStoreError
from bigT.storage import BlockCSR, BlockCSRWriter, PixelOrder, from_scipy, open as open_store, set_redirect


def _ref(A, dtype):
    """A as the store should hold it: cast, canonical, explicit zeros dropped."""
    R = sp.csr_array(A).astype(dtype)
    R.sum_duplicates()
    R.eliminate_zeros()
    return R


def _check_against(S, R):
    ts = S.tile_size
    n, m = R.shape
    assert S.shape == R.shape and S.nnz == R.nnz
    B = S.to_scipy()
    assert B.dtype == R.dtype and B.has_sorted_indices
    assert B.shape == R.shape and (B != R).nnz == 0
    stored = 0
    for i in range(S.grid[0]):
        r0, r1 = S.tile_row_range(i)
        assert (r0, r1) == (i * ts, min(n, (i + 1) * ts))
        row = S.get_tile_row(i)
        assert row.shape == (r1 - r0, m) and (row != R[r0:r1]).nnz == 0
        for j in range(S.grid[1]):
            c0, c1 = j * ts, min(m, (j + 1) * ts)
            ref = R[r0:r1, c0:c1]
            t = S.get_tile(i, j)
            assert t.shape == (r1 - r0, c1 - c0) == S.tile_shape(i, j)
            assert (t != ref).nnz == 0
            assert S.has_tile(i, j) == (ref.nnz > 0)
            stored += ref.nnz > 0
        assert list(S.tile_columns(i)) == [j for j in range(S.grid[1]) if S.has_tile(i, j)]
    assert S.n_tiles_stored == stored == int(S.tile_nnz.size)
    assert int(S.tile_nnz.sum()) == R.nnz
    np.testing.assert_array_equal(S.diagonal(), R.diagonal())
    rng = np.random.default_rng(0)
    x = rng.standard_normal(m)
    X = rng.standard_normal((m, 3))
    tol = 1e-4 if R.dtype == np.float32 else 1e-10
    np.testing.assert_allclose(S @ x, R.astype(np.float64) @ x, rtol=tol, atol=tol)
    np.testing.assert_allclose(S.matmul(X), R.astype(np.float64) @ X, rtol=tol, atol=tol)
    assert S.verify()["nnz"] == R.nnz


@settings(max_examples=25, deadline=None)
@given(n=st.integers(1, 40), m=st.integers(1, 40), density=st.floats(0.0, 0.6),
       tiles_per_side=st.integers(1, 5), dtype=st.sampled_from(["float32", "float64"]),
       seed=st.integers(0, 2**16), chunk=st.sampled_from([5, 16, 1 << 20]))
def test_roundtrip_matches_scipy(n, m, density, tiles_per_side, dtype, seed, chunk):
    ts = max(1, -(-max(n, m) // tiles_per_side))
    A = sp.random(n, m, density=density, format="csr", random_state=seed)
    saved = config.CHUNK_ELEMENTS
    config.CHUNK_ELEMENTS = chunk   # small chunks: tile arrays span many chunk files
    try:
        with tempfile.TemporaryDirectory() as d:
            S = from_scipy(A, os.path.join(d, "a.zarr"), tile_size=ts, dtype=dtype)
            assert S.dtype == np.dtype(dtype) and S.tile_size == ts
            _check_against(S, _ref(A, dtype))
            assert (open_store(os.path.join(d, "a.zarr")).to_scipy() != _ref(A, dtype)).nnz == 0
    finally:
        config.CHUNK_ELEMENTS = saved


def test_empty_rows_tiles_ragged_nonsquare(tmp_path):
    rng = np.random.default_rng(1)
    D = rng.random((23, 17)) * (rng.random((23, 17)) < 0.3)
    D[3] = 0                      # an empty row
    D[8:16, :] = 0                # an empty tile row (tile size 8)
    D[:, 8:16] = 0                # empty tile column
    A = sp.csr_array(D)
    S = from_scipy(A, tmp_path / "a.zarr", tile_size=8, dtype="float64")
    assert S.grid == (3, 3)
    assert S.tile_shape(2, 2) == (7, 1)
    assert not S.has_tile(1, 0) and S.get_tile(1, 0).nnz == 0
    assert list(S.tile_columns(1)) == []
    _check_against(S, _ref(A, "float64"))


def test_all_empty_matrix(tmp_path):
    A = sp.csr_array((30, 20), dtype=np.float64)
    S = from_scipy(A, tmp_path / "e.zarr", tile_size=7)
    assert S.nnz == 0 and S.n_tiles_stored == 0
    _check_against(S, _ref(A, "float64"))  # float64 in, float64 stored
    assert S.info()["zero_diagonal"] == 20


def test_dense_input_and_duplicates(tmp_path):
    coo = sp.coo_array((np.array([1.0, 2.0, 0.0]), (np.array([0, 0, 2]), np.array([1, 1, 2]))),
                       shape=(4, 4))
    S = from_scipy(coo, tmp_path / "d.zarr", tile_size=2)
    assert S.nnz == 1 and S.to_scipy()[0, 1] == 3.0   # duplicates summed, zero dropped
    D = np.arange(16.0).reshape(4, 4)
    S2 = from_scipy(D, tmp_path / "d2.zarr", tile_size=3, dtype="float64")
    np.testing.assert_array_equal(S2.to_scipy().toarray(), D)


@pytest.mark.parametrize("order", ["row-major", "tile-major"])
def test_pixel_order_roundtrip(tmp_path, order):
    H, W = 10, 9
    n = H * W
    A = sp.random(n, n, density=0.05, format="csr", random_state=3, dtype=np.float64) + sp.eye(n)
    A = sp.csr_array(A)
    S = from_scipy(A, tmp_path / "p.zarr", tile_size=32, dtype="float64", image_shape=(H, W),
                   pixel_order=order, image_tile=(4, 3))
    po = S.pixel_order
    assert po == PixelOrder((H, W), order, (4, 3))
    assert S.info()["pixel_order"] == po.to_attrs()
    perm = po.permutation
    # stored order: A_stored[k, l] = A_rowmajor[perm[k], perm[l]]
    assert (S.to_scipy(output_order="matrix") != A[perm][:, perm]).nnz == 0
    assert (S.to_scipy(output_order="row-major") != A).nnz == 0
    img = np.random.default_rng(0).random((H, W))
    np.testing.assert_allclose(S @ img.ravel(), A @ img.ravel(), rtol=1e-12)
    # the stored order, asked for explicitly: matrix-ordered vectors in and out
    out = po.to_images(S.matmul(po.to_matrix(img), order="matrix"))
    np.testing.assert_allclose(out, (A @ img.ravel()).reshape(H, W), rtol=1e-12)
    # input_order="matrix": A is taken as already in the stored order
    S2 = from_scipy(A, tmp_path / "q.zarr", tile_size=32, dtype="float64", image_shape=(H, W),
                    pixel_order=order, image_tile=(4, 3), input_order="matrix")
    assert (S2.to_scipy(output_order="matrix") != A).nnz == 0
    if order == "tile-major":
        assert not np.array_equal(perm, np.arange(n))
        # A was taken as stored order, so row-major output undoes the permutation on it
        assert (S2.to_scipy(output_order="row-major") != A[po.inverse_permutation][:, po.inverse_permutation]).nnz == 0


def test_writer_direct_and_metadata(tmp_path):
    A = sp.random(20, 20, density=0.2, format="csr", random_state=5)
    w = BlockCSRWriter(tmp_path / "w.zarr", A.shape, tile_size=6, dtype="float64",
                       metadata={"term": 0})
    for i in range(w.grid[0]):
        r0, r1 = w.tile_row_range(i)
        assert w.write_tile_row(i, A[r0:r1]) is True
    S = w.finalize()
    assert isinstance(S, BlockCSR)
    _check_against(S, _ref(A, "float64"))
    S.update_metadata(residual=1.5e-3, prune=1e-5)
    again = open_store(tmp_path / "w.zarr")
    assert again.metadata == {"term": 0, "residual": 1.5e-3, "prune": 1e-5}
    assert not [f for f in os.listdir(tmp_path / "w.zarr") if f.endswith(".tmp")]
    with pytest.raises(ValueError):
        S.update_metadata(bad=object())


def test_to_scipy_memory_limit_and_matmul_shape(tmp_path):
    A = sp.random(30, 30, density=0.3, format="csr", random_state=1)
    S = from_scipy(A, tmp_path / "m.zarr", tile_size=10)
    with pytest.raises(MemoryLimitError, match="m.zarr"):
        S.to_scipy(max_bytes=100)
    with pytest.raises(ShapeMismatchError):
        S @ np.ones(29)
    with pytest.raises(ShapeMismatchError):
        S.get_tile(3, 0)


def test_redirect_versioned_store(tmp_path):
    root = tmp_path / "inv.zarr"
    A0 = sp.random(12, 12, density=0.3, format="csr", random_state=0, dtype=np.float64)
    A1 = sp.random(12, 12, density=0.3, format="csr", random_state=1, dtype=np.float64)
    from_scipy(A0, root / "terms" / "0", tile_size=5, dtype="float64")
    set_redirect(root, "terms/0")
    assert (open_store(root).to_scipy() != A0).nnz == 0
    from_scipy(A1, root / "terms" / "1", tile_size=5, dtype="float64")
    set_redirect(root, "terms/1")
    S = open_store(root)
    assert (S.to_scipy() != A1).nnz == 0
    assert S.path == root / "terms" / "1" and S.redirected_from == root
    import zarr  # every level is an explicit zarr v3 group another reader can walk
    assert "terms" in zarr.open_group(root, mode="r")
    with pytest.raises(StoreError):
        set_redirect(root, "../elsewhere")
    with pytest.raises(StoreError):
        set_redirect(root, "terms/9")
    w = BlockCSRWriter(root / "terms" / "2", (12, 12), tile_size=5)
    with pytest.raises(IncompleteStoreError):
        set_redirect(root, "terms/2")
    del w
    # one level of redirect is followed, not two
    outer = tmp_path / "outer.zarr"
    from_scipy(A0, outer / "inner" / "s", tile_size=5)
    set_redirect(outer / "inner", "s")
    from bigT.atomic import atomic_write_json
    from bigT.storage._format import group_json
    atomic_write_json(outer / "zarr.json", group_json(
        {"bigT": {"format": "bigT-block-csr", "version": 1, "redirect": "inner"}}))
    assert open_store(outer / "inner").nnz == sp.csr_array(A0).astype(np.float32).nnz
    with pytest.raises(StoreError, match="another redirect"):
        open_store(outer)


@pytest.mark.parametrize("given, stored", [(np.float64, "float64"), (np.float32, "float32"),
                                           (np.int64, "float32"), (bool, "float32")])
def test_from_scipy_keeps_the_float_dtype_unless_told(tmp_path, given, stored):
    A = sp.csr_array(np.array([[1, 0], [0, 1]], dtype=given))
    assert from_scipy(A, tmp_path / "a.zarr").dtype == np.dtype(stored)
    assert from_scipy(A, tmp_path / "b.zarr", dtype="float32").dtype == np.float32


@pytest.mark.parametrize("numba_path", [False, True])
def test_tile_rows_joined_on_both_kernel_paths(tmp_path, monkeypatch, numba_path):
    """get_tile_row joins a row's tiles (numba above config.KERNEL_NUMPY_MAX_WORK
    entries, its numpy twin below): ragged last tile row and column, whole rows and
    rows restricted to some tile columns, against scipy."""
    if numba_path:
        monkeypatch.setattr(config, "KERNEL_NUMPY_MAX_WORK", -1)
    A = sp.random_array((70, 90), density=0.2, format="csr", dtype=np.float32,
                        rng=np.random.default_rng(4))
    S = from_scipy(A, tmp_path / "A.zarr", tile_size=16)
    R = _ref(A, np.float32)
    for i in range(S.grid[0]):
        r0, r1 = S.tile_row_range(i)
        assert (S.get_tile_row(i) != R[r0:r1]).nnz == 0
        cols = list(S.tile_columns(i))[::2]
        mask = np.zeros(90, bool)
        for j in cols:
            mask[j * 16:(j + 1) * 16] = True
        part = S.get_tile_row(i, columns=cols)
        assert part.has_sorted_indices
        np.testing.assert_array_equal(part.toarray(), R[r0:r1].toarray() * mask[None, :])
