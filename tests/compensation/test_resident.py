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
    assert R.nbytes == resident_bytes_needed(store, "float32")
    assert R.nbytes == A.nnz * 6 + N * 3 * 4  # 6 bytes an entry, 3 int32 pointers a row
    assert load_bytes_needed(store, "float32") > R.nbytes
    diff = R.to_scipy() - A
    assert diff.nnz == 0 or abs(diff).max() == 0  # the same matrix


@pytest.mark.parametrize("k", [1, 5])
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


@pytest.mark.parametrize("k", [1, 4])
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
