"""bigT.kernels against scipy.sparse and dense numpy references."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from bigT import config
from bigT.errors import InvalidMatrixError, ShapeMismatchError
from bigT.kernels import (
    add_diag_scaled,
    choose_index_dtype,
    diagonal,
    prune,
    scale_cols,
    scale_cols_off_diagonal,
    scale_rows,
    spgemm,
    spmm_dense,
)

SETTINGS = settings(max_examples=30, deadline=None)
DTYPES = st.sampled_from([np.float32, np.float64])


def _assert_canonical(C):
    """Sorted, duplicate-free rows, consistent arrays, no explicit zeros."""
    assert isinstance(C, sp.csr_array)
    assert C.indptr.dtype == C.indices.dtype
    assert C.indptr[0] == 0 and C.indptr[-1] == C.indices.shape[0] == C.data.shape[0]
    assert np.all(np.diff(C.indptr) >= 0)
    rows = np.repeat(np.arange(C.shape[0]), np.diff(C.indptr))
    same_row = rows[1:] == rows[:-1]
    assert np.all(np.diff(C.indices.astype(np.int64))[same_row] > 0)
    if C.nnz:
        assert C.indices.min() >= 0 and C.indices.max() < C.shape[1]


@st.composite
def sparse(draw, shape, *, dyadic=False, dtype=np.float64, sorted_rows=None):
    """A csr_array of the given shape: random density (empty rows, 0 nnz included).

    dyadic values k/8 (|k| <= 16) make every product and sum exact in float32 and
    float64, so thresholded results can be compared with ``==`` (no borderline ties).
    Unsorted rows are shuffled within each row (still duplicate-free).
    """
    m, n = shape
    density = draw(st.sampled_from([0.0, 0.1, 0.3, 0.7, 1.0]))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    mask = rng.random((m, n)) < density
    if dyadic:
        vals = rng.integers(1, 17, size=(m, n)) * rng.choice([-1, 1], size=(m, n)) / 8.0
    else:
        vals = rng.standard_normal((m, n)) * 10.0 ** rng.uniform(-3, 1, size=(m, n))
    dense = np.where(mask, vals, 0.0).astype(dtype)
    A = sp.csr_array(dense)
    if sorted_rows is None:
        sorted_rows = draw(st.booleans())
    if not sorted_rows and A.nnz:
        indices, data = A.indices.copy(), A.data.copy()
        for i in range(m):
            s, e = A.indptr[i], A.indptr[i + 1]
            perm = rng.permutation(e - s) + s
            indices[s:e], data[s:e] = indices[perm], data[perm]
        A = sp.csr_array((data, indices, A.indptr.copy()), shape=(m, n))
    return A


def dims(lo=0, hi=12):
    return st.integers(lo, hi)


@st.composite
def product_pair(draw, *, dyadic=False, lo=0):
    m, k, n = draw(dims(lo)), draw(dims(lo)), draw(dims(lo))
    da, db = draw(DTYPES), draw(DTYPES)
    A = draw(sparse((m, k), dyadic=dyadic, dtype=da))
    B = draw(sparse((k, n), dyadic=dyadic, dtype=db))
    return A, B


def _dense64(A):
    return np.asarray(A.toarray(), dtype=np.float64)


# --- spgemm --------------------------------------------------------------------------


@SETTINGS
@given(product_pair(), st.sampled_from([None, "rows", "grouped"]), st.sampled_from([1, 2]))
def test_spgemm_matches_scipy(pair, method, n_threads):
    A, B = pair
    C = spgemm(A, B, method=method, n_threads=n_threads)
    ref = A @ B
    assert C.shape == ref.shape
    assert C.dtype == np.result_type(A.dtype, B.dtype)
    _assert_canonical(C)
    rtol = 1e-5 if C.dtype == np.float32 else 1e-12
    R = _dense64(A) @ _dense64(B)
    scale = np.abs(_dense64(A)) @ np.abs(_dense64(B))
    assert np.all(np.abs(C.toarray() - R) <= rtol * scale + 1e-30)


@SETTINGS
@given(product_pair(dyadic=True), st.sampled_from([None, "rows", "grouped"]), st.integers(0, 200))
def test_spgemm_threshold_equals_scipy_then_prune(pair, method, t64):
    A, B = pair
    # Products of k/8 values sum to multiples of 1/64 (exactly, in either dtype): a
    # threshold at an odd multiple of 1/128 is never tied.
    threshold = (2 * t64 + 1) / 128.0
    C = spgemm(A, B, threshold=threshold, method=method, n_threads=2)
    R = _dense64(A) @ _dense64(B)
    want = np.where(np.abs(R) >= threshold, R, 0.0)
    _assert_canonical(C)
    np.testing.assert_array_equal(C.toarray().astype(np.float64), want)
    assert C.nnz == np.count_nonzero(want)


@SETTINGS
@given(product_pair(dyadic=True))
def test_spgemm_threshold_zero_is_scipys_pattern(pair):
    A, B = pair
    ref = sp.csr_array(A @ B)
    ref.eliminate_zeros()
    for method in (None, "rows", "grouped"):
        C = spgemm(A, B, method=method)
        assert C.nnz == ref.nnz
        np.testing.assert_array_equal(C.toarray(), ref.toarray())


def _top_k_reference(R, mask, k):
    """Per row, the k largest |v| among mask (ties: smaller column), dense."""
    out = np.zeros_like(R)
    for i in range(R.shape[0]):
        cols = np.flatnonzero(mask[i])
        order = np.lexsort((cols, -np.abs(R[i, cols])))
        keep = cols[order[:k]]
        out[i, keep] = R[i, keep]
    return out


@SETTINGS
@given(product_pair(dyadic=True), st.integers(1, 6), st.sampled_from([0.0, 0.5 / 64]),
       st.sampled_from([None, "rows", "grouped"]))
def test_spgemm_top_k(pair, k, threshold, method):
    A, B = pair
    C = spgemm(A, B, threshold=threshold, top_k=k, method=method)
    R = _dense64(A) @ _dense64(B)
    mask = (R != 0) & (np.abs(R) >= threshold)
    _assert_canonical(C)
    assert np.all(np.diff(C.indptr) <= k)
    np.testing.assert_array_equal(C.toarray().astype(np.float64), _top_k_reference(R, mask, k))


def test_spgemm_all_pruned_and_empty():
    A = sp.csr_array(np.full((4, 3), 1e-3))
    C = spgemm(A, A.T, threshold=1.0)
    assert C.shape == (4, 4) and C.nnz == 0
    _assert_canonical(C)
    for shape_a, shape_b in [((0, 3), (3, 5)), ((4, 0), (0, 5)), ((4, 3), (3, 0))]:
        C = spgemm(sp.csr_array(shape_a), sp.csr_array(shape_b))
        assert C.shape == (shape_a[0], shape_b[1]) and C.nnz == 0


def test_spgemm_large_work_uses_threads_and_matches():
    """Enough multiply-adds to split rows over threads (groups and both emissions)."""
    rng = np.random.default_rng(3)
    n = 600
    A = sp.random_array((n, n), density=0.05, format="csr", rng=rng, dtype=np.float64)
    # A banded part too: neighbouring rows share columns (the grouped path proper).
    band = sp.diags_array([rng.random(n - abs(o)) for o in range(-20, 21)],
                          offsets=list(range(-20, 21)), format="csr")
    for M in (A, sp.csr_array(band), sp.csr_array(A + band)):
        ref = _dense64(M) @ _dense64(M)
        for method in (None, "rows", "grouped"):
            C = spgemm(M, M, method=method, n_threads=2, threshold=1e-3)
            np.testing.assert_allclose(
                C.toarray(), np.where(np.abs(ref) >= 1e-3, ref, 0), rtol=1e-12, atol=0
            )


def test_spgemm_duplicates_are_summed():
    A = sp.csr_array((np.array([1.0, 2.0, 3.0]), np.array([1, 1, 0]), np.array([0, 3])),
                     shape=(1, 2))
    B = sp.csr_array(np.array([[1.0, 0.0], [0.0, 1.0]]))
    np.testing.assert_array_equal(spgemm(A, B).toarray(), [[3.0, 3.0]])
    np.testing.assert_array_equal(spgemm(B, A.T).toarray(), [[3.0], [3.0]])


def test_spgemm_int64_indices():
    rng = np.random.default_rng(0)
    A = sp.random_array((30, 20), density=0.3, format="csr", rng=rng)
    B = sp.random_array((20, 25), density=0.3, format="csr", rng=rng)
    C = spgemm(A, B, index_dtype=np.int64)
    assert C.indices.dtype == np.int64 and C.indptr.dtype == np.int64
    np.testing.assert_allclose(C.toarray(), (A @ B).toarray(), rtol=1e-12)
    A64 = sp.csr_array((A.data, A.indices.astype(np.int64), A.indptr.astype(np.int64)),
                       shape=A.shape)
    np.testing.assert_allclose(spgemm(A64, B).toarray(), (A @ B).toarray(), rtol=1e-12)


def test_choose_index_dtype():
    big = np.iinfo(np.int32).max
    assert choose_index_dtype(10, 10) == np.int32
    assert choose_index_dtype(big, big) == np.int32
    assert choose_index_dtype(big + 1, 0) == np.int64
    assert choose_index_dtype(0, big + 1) == np.int64
    assert choose_index_dtype(5, 5, np.int64) == np.int64
    with pytest.raises(InvalidMatrixError):
        choose_index_dtype(0, big + 1, np.int32)


def test_spgemm_checks():
    A = sp.csr_array(np.eye(3))
    with pytest.raises(ShapeMismatchError, match="B has 2 rows"):
        spgemm(A, sp.csr_array(np.eye(2)))
    bad = sp.csr_array((np.array([1.0]), np.array([5]), np.array([0, 1, 1, 1])), shape=(3, 3))
    with pytest.raises(InvalidMatrixError, match="B: column index out of range"):
        spgemm(A, bad)
    nan = sp.csr_array(np.array([[np.nan, 0, 0], [0, 1, 0], [0, 0, 1]]))
    with pytest.raises(InvalidMatrixError, match="A: NaN or Inf"):
        spgemm(nan, A)
    with pytest.raises(ValueError, match="threshold"):
        spgemm(A, A, threshold=-1)
    with pytest.raises(ValueError, match="top_k"):
        spgemm(A, A, top_k=0)
    with pytest.raises(InvalidMatrixError, match="complex"):
        spgemm(sp.csr_array(np.eye(3, dtype=complex)), A)


# --- prune, add_diag_scaled, scaling, diagonal ----------------------------------------


@SETTINGS
@given(st.data(), DTYPES, st.integers(0, 40), st.one_of(st.none(), st.integers(1, 5)))
def test_prune(data, dtype, t, k):
    A = data.draw(sparse((data.draw(dims()), data.draw(dims())), dyadic=True, dtype=dtype))
    threshold = (2 * t + 1) / 16.0  # values are multiples of 1/8: no ties
    C = prune(A, threshold, top_k=k)
    _assert_canonical(C)
    assert C.dtype == A.dtype
    D = _dense64(A)
    mask = np.abs(D) >= threshold
    want = np.where(mask, D, 0.0) if k is None else _top_k_reference(D, mask, k)
    np.testing.assert_array_equal(C.toarray(), want)


@SETTINGS
@given(st.data(), DTYPES, DTYPES)
def test_add_diag_scaled(data, da, db):
    m, n = data.draw(dims()), data.draw(dims())
    A = data.draw(sparse((m, n), dyadic=True, dtype=da))
    B = data.draw(sparse((m, n), dyadic=True, dtype=db))
    d = np.random.default_rng(data.draw(st.integers(0, 999))).integers(-4, 5, m) / 4.0
    C = add_diag_scaled(A, d, B)
    _assert_canonical(C)
    assert C.dtype == np.result_type(da, db, d.dtype)
    want = _dense64(A) + d[:, None] * _dense64(B)
    np.testing.assert_array_equal(C.toarray(), want)
    assert C.nnz == np.count_nonzero(want)


@SETTINGS
@given(st.data(), DTYPES)
def test_scale_rows_cols_diagonal(data, dtype):
    m, n = data.draw(dims()), data.draw(dims())
    A = data.draw(sparse((m, n), dtype=dtype))
    rng = np.random.default_rng(data.draw(st.integers(0, 999)))
    dr, dc = rng.standard_normal(m), rng.standard_normal(n).astype(np.float32)
    R = scale_rows(A, dr)
    _assert_canonical(R)
    assert R.dtype == np.result_type(dtype, dr.dtype)
    np.testing.assert_allclose(R.toarray(), dr[:, None] * _dense64(A), rtol=1e-6)
    S = scale_cols(A, dc)
    _assert_canonical(S)
    assert S.dtype == np.result_type(dtype, dc.dtype)
    np.testing.assert_allclose(S.toarray(), _dense64(A) * dc[None, :], rtol=1e-6)
    np.testing.assert_array_equal(diagonal(A), A.diagonal())


@SETTINGS
@given(st.data(), DTYPES)
def test_scale_cols_off_diagonal(data, dtype):
    """A @ diag(d) with the entries (i, i + offset) left out, for a row block of a
    larger matrix starting at row ``offset``: against dense numpy."""
    m, n = data.draw(dims()), data.draw(dims())
    A = data.draw(sparse((m, n), dtype=dtype))
    offset = data.draw(st.integers(0, n + 2))  # past the columns: nothing left out
    d = np.random.default_rng(data.draw(st.integers(0, 999))).uniform(0.5, 2, n)
    d = d.astype(data.draw(DTYPES))
    S = scale_cols_off_diagonal(A, d, offset)
    _assert_canonical(S)
    assert S.dtype == np.result_type(dtype, d.dtype)
    want = _dense64(A) * d[None, :]
    rows = np.arange(m)
    on = rows + offset < n
    want[rows[on], rows[on] + offset] = 0.0
    np.testing.assert_allclose(S.toarray(), want, rtol=1e-6)
    assert S.nnz == A.nnz - np.count_nonzero(_dense64(A)[rows[on], rows[on] + offset])
    if A.has_canonical_format:  # what checked=False trusts (a store's tile row)
        U = scale_cols_off_diagonal(A, d, offset, checked=False)
        for got, ref in ((U.indptr, S.indptr), (U.indices, S.indices), (U.data, S.data)):
            assert got.dtype == ref.dtype and np.array_equal(got, ref)


def test_elementwise_checks():
    A = sp.csr_array(np.eye(3))
    with pytest.raises(ShapeMismatchError, match="d must have shape"):
        scale_rows(A, np.ones(2))
    with pytest.raises(ShapeMismatchError, match="d must have shape"):
        scale_cols(A, np.ones(4))
    with pytest.raises(ShapeMismatchError, match="B has shape"):
        add_diag_scaled(A, np.ones(3), sp.csr_array(np.eye(4)))
    with pytest.raises(InvalidMatrixError, match="d holds NaN"):
        add_diag_scaled(A, np.array([1.0, np.nan, 1.0]), A)


# --- spmm_dense ------------------------------------------------------------------------


@SETTINGS
@given(st.data(), DTYPES, DTYPES, st.sampled_from([None, 1, 3, 64]), st.booleans())
def test_spmm_dense(data, da, dx, k, with_out):
    m, n = data.draw(dims()), data.draw(dims())
    A = data.draw(sparse((m, n), dtype=da))
    rng = np.random.default_rng(data.draw(st.integers(0, 999)))
    shape = (n,) if k is None else (n, k)
    X = rng.standard_normal(shape).astype(dx)
    want = _dense64(A) @ X.astype(np.float64)
    scale = np.abs(_dense64(A)) @ np.abs(X.astype(np.float64))
    rdt = np.result_type(da, dx)
    rtol = 1e-5 if rdt == np.float32 else 1e-12
    if with_out:
        out0 = rng.standard_normal(want.shape).astype(rdt)
        out = out0.copy()
        Y = spmm_dense(A, X, out=out)
        assert Y is out
        want = want + out0
        scale = scale + np.abs(out0)
    else:
        Y = spmm_dense(A, X)
        assert Y.dtype == rdt
    assert Y.shape == want.shape
    assert np.all(np.abs(Y - want) <= rtol * scale + 1e-30)


def test_spmm_dense_threads_and_strided_out():
    rng = np.random.default_rng(5)
    A = sp.random_array((500, 400), density=0.1, format="csr", rng=rng)
    X = rng.standard_normal((400, 64))
    np.testing.assert_allclose(spmm_dense(A, X, n_threads=2), A @ X, rtol=1e-12, atol=1e-12)
    out = np.zeros((64, 500)).T  # Fortran-ordered view
    spmm_dense(A, X, out=out)
    np.testing.assert_allclose(out, A @ X, rtol=1e-12, atol=1e-12)
    x = rng.standard_normal(400)
    np.testing.assert_allclose(spmm_dense(A, x, n_threads=2), A @ x, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("shape", [(12, 9), (3000, 2000)])  # the small path, numba's
@pytest.mark.parametrize("k", [1, 5])
@pytest.mark.parametrize("da", [np.float32, np.float64])
def test_spmm_dense_absolute(shape, k, da):
    """|A| @ X (entries of both signs), A left as it was; float32 A with float64 X."""
    rng = np.random.default_rng(11)
    A = sp.random_array(shape, density=0.05, format="csr", rng=rng,
                        data_sampler=rng.standard_normal).astype(da)
    before = A.data.copy()
    X = rng.standard_normal((shape[1], k))
    want = np.abs(_dense64(A)) @ X
    Y = spmm_dense(A, X, n_threads=2, absolute=True)
    np.testing.assert_allclose(Y, want, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(A.data, before)
    np.testing.assert_allclose(spmm_dense(A, X, n_threads=2), _dense64(A) @ X,
                               rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("k", [2, 3, 4, 5, 8, 9])
@pytest.mark.parametrize("da,dx", [(np.float32, np.float32), (np.float32, np.float64),
                                   (np.float64, np.float64)])
@pytest.mark.parametrize("absolute", [False, True])
def test_spmm_dense_sums_each_column_in_row_order(monkeypatch, k, da, dx, absolute):
    """For k > 1 each entry of A @ X is the sum of its row's terms taken in the row's
    order, in X's dtype, then added to ``out``: the same bits as a sequential loop
    (the kernel sums four columns at a time in registers; the residual estimates
    compare terms by these sums)."""
    monkeypatch.setattr(config, "KERNEL_NUMPY_MAX_WORK", 0)  # the numba kernel
    rng = np.random.default_rng(17 + k)
    A = sp.random_array((300, 200), density=0.2, format="csr", rng=rng,
                        data_sampler=rng.standard_normal).astype(da)
    X = rng.standard_normal((200, k)).astype(dx)
    out0 = rng.standard_normal((300, k)).astype(dx)
    got = spmm_dense(A, X, out=out0.copy(), n_threads=2, absolute=absolute)
    want = out0.copy()
    for i in range(A.shape[0]):
        lo, hi = A.indptr[i], A.indptr[i + 1]
        if hi == lo:
            continue
        a = np.abs(A.data[lo:hi]) if absolute else A.data[lo:hi]
        terms = a[:, None].astype(dx) * X[A.indices[lo:hi]]
        want[i] += np.add.accumulate(terms, axis=0)[-1]  # strictly in order
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("k", [1, 2, 4, 6])
def test_spmm_dense_kernel_refuses_bad_index(monkeypatch, k):
    """The numba kernel's index check, fused into the first columns' loop for k >= 4:
    an index out of range is reported, its row and the rows after it not added."""
    monkeypatch.setattr(config, "KERNEL_NUMPY_MAX_WORK", 0)
    bad = sp.csr_array((np.array([1.0, 2.0, 3.0]), np.array([0, 1, 7]),
                        np.array([0, 1, 3, 3])), shape=(3, 3))
    with pytest.raises(InvalidMatrixError, match="column index out of range"):
        spmm_dense(bad, np.ones((3, k)), n_threads=1)


def test_spmm_dense_checks():
    A = sp.csr_array(np.eye(3))
    with pytest.raises(ShapeMismatchError, match="X has 2 rows"):
        spmm_dense(A, np.ones((2, 4)))
    with pytest.raises(ShapeMismatchError, match="out must have shape"):
        spmm_dense(A, np.ones((3, 4)), out=np.zeros((3, 5)))
    with pytest.raises(InvalidMatrixError, match="NaN or Inf"):
        spmm_dense(A, np.array([1.0, np.nan, 0.0]))
    bad = sp.csr_array((np.array([1.0]), np.array([7]), np.array([0, 1, 1, 1])), shape=(3, 3))
    with pytest.raises(InvalidMatrixError, match="column index out of range"):
        spmm_dense(bad, np.ones(3))


def test_spgemm_wide_sparse_rows():
    """Few entries spread over a wide span: the grouped kernel's marked-block emission
    (and the rows kernel's sorted-list emission)."""
    rng = np.random.default_rng(11)
    A = sp.random_array((200, 3000), density=0.001, format="csr", rng=rng)
    B = sp.random_array((3000, 5000), density=0.0006, format="csr", rng=rng)
    ref = _dense64(A) @ _dense64(B)
    for method in (None, "rows", "grouped"):
        for threshold in (0.0, 0.05):
            C = spgemm(A, B, method=method, threshold=threshold)
            _assert_canonical(C)
            want = np.where(np.abs(ref) >= threshold, ref, 0.0)
            np.testing.assert_allclose(C.toarray(), want, rtol=1e-12, atol=0)
            assert C.nnz == np.count_nonzero(want)


def test_spgemm_reuses_its_workspace_cleanly(backend):
    """Calls of one shape share a kernel workspace (accumulators, marks, stamps): a run
    of different products, each against scipy, catches any state one call leaves to
    the next (a stale stamp once merged the rows of two groups)."""
    rng = np.random.default_rng(7)
    for _ in range(40):
        A = sp.random_array((40, 30), density=rng.uniform(0.05, 0.6), random_state=rng,
                            format="csr")
        B = sp.random_array((30, 30), density=rng.uniform(0.05, 0.6), random_state=rng,
                            format="csr")
        C = spgemm(A, B, method="grouped", n_threads=int(rng.integers(1, 3)))
        np.testing.assert_allclose(C.toarray(), (A @ B).toarray(), rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("method", ["grouped", "rows"])
def test_spgemm_rows_spanning_far_apart_columns(backend, method):
    """Rows whose columns lie in two far-apart regions (a pixel seeing across the
    corner's fold) and share few columns with their neighbours: the kernel lists
    their columns instead of scanning the whole span; same entries as scipy."""
    rng = np.random.default_rng(3)
    n = 200_000
    rows = np.repeat(np.arange(64), 6)
    cols = np.where(np.arange(rows.size) % 2, rng.integers(0, 50, rows.size),
                    rng.integers(n - 50, n, rows.size))
    A = sp.csr_array((rng.random(rows.size), (rows, cols)), shape=(64, n))
    B = sp.csr_array((rng.random(n), (np.arange(n), (np.arange(n) * 7) % n)), shape=(n, n))
    C = spgemm(A, B, method=method, threshold=1e-3)
    R = sp.csr_array(A @ B)
    R.data[np.abs(R.data) < 1e-3] = 0
    R.eliminate_zeros()
    assert C.nnz == R.nnz > 0
    assert abs(C - R).max() <= 1e-12
