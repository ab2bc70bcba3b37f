"""X held in memory (bigT.compensation.resident): the panel layout, both precisions,
both kernels, against scipy."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT.compensation.resident import (
    F16_TABLE,
    load_bytes_needed,
    load_resident,
    resident_bytes_needed,
)
from bigT.errors import MemoryLimitError, ShapeMismatchError

N = 70_000  # > 65536 columns: two panels of 16-bit indices


@pytest.fixture(scope="module")
def wide(tmp_path_factory):
    """A sparse N x N store whose rows reach both panels, with values over 10 decades
    and of both signs (row scales of the float16 encoding)."""
    rng = np.random.default_rng(3)
    per = 6
    rows = np.repeat(np.arange(N), per)
    cols = np.concatenate([rng.integers(0, N, N * (per - 2)), np.arange(N),
                           (np.arange(N) * 7919) % N]).reshape(per, N).T.ravel()
    vals = rng.uniform(-1, 1, rows.size) * 10.0 ** rng.integers(-6, 4, rows.size)
    A = sp.csr_array((vals.astype(np.float32), (rows, cols)), shape=(N, N))
    A.sum_duplicates()
    path = tmp_path_factory.mktemp("resident") / "A.zarr"
    store = bigT.from_scipy(A, path, tile_size=8192, dtype="float32")
    return store, sp.csr_array(A.astype(np.float32))


def test_layout_counts_and_bytes(wide):
    store, A = wide
    R = load_resident(store, "float32")
    assert R.n_panels == 2 and R.nnz == A.nnz and R.indices.dtype == np.uint16
    rows = np.repeat(np.arange(N), np.diff(A.indptr))
    segments = np.unique(rows * 2 + (A.indices >> 16)).size  # (row, panel) pairs held
    assert R.n_segments == segments
    # 6 bytes an entry, 6 a segment (uint16 panel, int32 start), one int32 a row
    assert R.nbytes == A.nnz * 6 + segments * 6 + 4 + (N + 1) * 4
    # the bound from the tile index: every row reaches both panels at most
    assert R.nbytes <= resident_bytes_needed(store, "float32") <= A.nnz * 6 + 2 * N * 6 + 4 \
        + (N + 1) * 4
    assert load_bytes_needed(store, "float32") > R.nbytes
    diff = R.to_scipy() - A
    assert diff.nnz == 0 or abs(diff).max() == 0  # the same matrix


@pytest.mark.parametrize("k", [1, 5, 8])  # 8: the unrolled kernel
@pytest.mark.parametrize("threads", [1, 2])
def test_float32_products_match_scipy(wide, k, threads):
    store, A = wide
    R = load_resident(store, "float32")
    V = np.random.default_rng(k).uniform(0, 1, (N, k)).astype(np.float32)
    ref = A.astype(np.float64) @ V.astype(np.float64)
    got = R.matmul(V[:, 0] if k == 1 else V, n_threads=threads).reshape(N, k)
    # float32 sums of ~6 terms: a few ulps of sum |a_ij v_j|
    bound = 1e-6 * (abs(A).astype(np.float64) @ V.astype(np.float64)) + 1e-30
    assert np.all(np.abs(got - ref) <= bound)


@pytest.mark.parametrize("k", [1, 4, 8])
def test_float16_error_within_its_precision(wide, k):
    """|y16 - y32| <= (2^-11 + float32 rounding) (|X| |v|) + 2^-40 s_i nnz_i: binary16's
    relative rounding in the normal range the row scale guarantees, and the absolute
    floor of its subnormals."""
    store, A = wide
    R16 = load_resident(store, "float16")
    assert R16.values.nbytes + R16.indices.nbytes == 4 * A.nnz  # 2 + 2 bytes an entry
    V = np.random.default_rng(10 + k).uniform(0, 1, (N, k)).astype(np.float32)
    ref = A.astype(np.float64) @ V.astype(np.float64)
    got = R16.matmul(V, n_threads=2)
    absA = abs(A).astype(np.float64)
    scale = R16.row_scale.astype(np.float64) * 2.0 ** 15  # s_i
    nnz_row = np.diff(A.indptr)
    bound = (2.0 ** -11 + 1e-6) * (absA @ V.astype(np.float64)) \
        + (2.0 ** -40 * scale * nnz_row)[:, None]
    assert np.all(np.abs(got - ref) <= bound)
    assert np.abs(got - ref).max() > 0  # it is a narrower type


def test_f16_table_decodes_every_pattern():
    bits = np.arange(1 << 16, dtype=np.uint32).astype(np.uint16)
    want = bits.view(np.float16).astype(np.float32)
    np.testing.assert_array_equal(F16_TABLE.view(np.uint32)[~np.isnan(want)],
                                  want.view(np.uint32)[~np.isnan(want)])


def test_small_product_runs_on_scipy(tmp_path):
    """Below config.KERNEL_NUMPY_MAX_WORK the product is scipy's (no kernel compiled),
    and agrees with the dense product."""
    A = np.random.default_rng(0).uniform(-1, 1, (20, 30)) * (np.random.default_rng(1).random(
        (20, 30)) < 0.3)
    store = bigT.from_scipy(sp.csr_array(A), tmp_path / "s.zarr", tile_size=8, dtype="float32")
    for precision, rtol in (("float32", 1e-6), ("float16", 2.0 ** -10)):
        R = load_resident(store, precision)
        v = np.linspace(0, 1, 30)
        assert np.all(np.abs(R @ v - A @ v) <= rtol * (np.abs(A) @ v) + 1e-12)


def test_memory_limit_and_shapes(wide):
    store, _ = wide
    with pytest.raises(MemoryLimitError, match="holding X in memory needs"):
        load_resident(store, memory_limit=1 << 20)
    R = load_resident(store)
    with pytest.raises(ShapeMismatchError):
        R.matmul(np.ones(N + 1))


@pytest.mark.parametrize("precision", ["float32", "float16"])
@pytest.mark.parametrize("k", [1, 3, 8])
def test_segments_skip_empty_panels_and_rows(tmp_path, precision, k):
    """Rows that reach the first and third panels and not the second, rows in one panel,
    and empty rows: only the segments held are kept, and both kernels agree with
    scipy."""
    n = 3 * 65536 + 100
    rng = np.random.default_rng(7)
    rows = np.arange(0, n, 3)  # every third row has entries; the others are empty
    first = rng.integers(0, 65536, rows.size)
    third = rng.integers(2 * 65536, 3 * 65536, rows.size)
    one_panel = rows % 2 == 0  # half of them in the third panel only
    r = np.concatenate([rows[~one_panel], rows])
    c = np.concatenate([first[~one_panel], third])
    A = sp.csr_array((rng.uniform(0.1, 1, r.size).astype(np.float32), (r, c)), shape=(n, n))
    store = bigT.from_scipy(A, tmp_path / "gaps.zarr", tile_size=65536, dtype="float32")
    R = load_resident(store, precision)
    assert R.n_panels == 4 and R.n_segments == A.nnz  # one entry per segment here
    assert set(np.unique(R.seg_panel)) == {0, 2}
    V = rng.uniform(0, 1, (n, k)).astype(np.float32)
    ref = A.astype(np.float64) @ V.astype(np.float64)
    got = R.matmul(V, n_threads=2)
    rtol = 1e-6 if precision == "float32" else 2.0 ** -10
    assert np.all(np.abs(got - ref) <= rtol * np.abs(ref))
    assert np.all(got[1::3] == 0) and np.all(got[2::3] == 0)  # the empty rows
