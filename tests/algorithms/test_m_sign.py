"""Whether M = I - T F^-1 has no positive entry (which the spectral radius's bracket
needs): known from the read of T's diagonal (FirstBounce.m_nonpositive: grey, F =
diag T, T without a negative entry), else read from M's rows in a pass of its own. The
two answers agree wherever the shortcut answers; the pass runs wherever it does not;
and out of core, T's tile rows read for the diagonal are the ones M is made from (T
decoded once before term 1), the inverse unchanged."""

import numpy as np
import pytest

import bigT
from bigT.algorithms import divergence
from bigT.algorithms.matvecs import MatVecs
from bigT.storage import block_csr

from inverse_helpers import random_dominant


def _transport(case: str) -> np.ndarray:
    """300 x 300: nonnegative; with a negative entry off the diagonal; with pixels left
    out (zero row and column, so F^-1 = 0 there); both."""
    A = random_dominant(300, seed=4, density=0.05)
    case = case.split()
    if "left-out" in case:
        for p in (5, 77, 150, 299):
            A[p, :] = 0
            A[:, p] = 0
    if "negative" in case:
        A[10, 200] = -1e-4
        A[123, 0] = -3e-5
    return A


def _dense_m_nonpositive(A: np.ndarray, f: np.ndarray) -> bool:
    """M = D - A F^-1 formed densely (F = diag f, 0 on pixels left out), M's diagonal 0
    where f is A's diagonal; whether it has no positive entry."""
    finv = np.where(f > 0, 1 / np.where(f > 0, f, 1), 0.0)
    M = -(A * finv[None, :])
    np.fill_diagonal(M, 0.0)
    return bool(M.max() <= 0)


def _answers(monkeypatch, T, tmp_path, first_bounce, in_memory):
    """(the shortcut applied, the engine's answer, the pass's answer) of one run."""
    seen = []
    real = divergence.estimate_radius

    def spy(matvecs, seed):
        lay = matvecs.layout
        passed = matvecs.apply_M(np.zeros((lay.n, 1)), largest=True).max(initial=0.0) <= 0
        seen.append((lay.fb.m_nonpositive, matvecs.m_nonpositive(), bool(passed)))
        return real(matvecs, seed)

    monkeypatch.setattr(divergence, "estimate_radius", spy)
    monkeypatch.setattr(divergence.config, "SPECTRAL_RADIUS_DENSE_MAX", 16)
    bigT.stratified_inverse(T, tmp_path / f"X-{len(list(tmp_path.iterdir()))}.zarr",
                            terms=1, first_bounce=first_bounce, in_memory=in_memory,
                            force=True, progress=False)
    (answer,) = seen
    return answer


@pytest.mark.parametrize("in_memory", [False, True])
@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("case", ["nonnegative", "negative", "left-out",
                                  "left-out negative"])  # words of _transport
def test_the_shortcut_gives_the_passes_answer(tmp_path, make_store, monkeypatch, case,
                                              dtype, in_memory):
    A = _transport(case)
    T = make_store(A, tile_size=64, dtype=dtype)
    shortcut, answer, passed = _answers(monkeypatch, T, tmp_path, "diag", in_memory)
    assert shortcut == ("negative" not in case.split())  # taken exactly where it applies
    assert answer == passed == _dense_m_nonpositive(A, np.diag(A))


@pytest.mark.parametrize("first_bounce", ["identity", "vector"])
def test_other_first_bounces_read_m(tmp_path, make_store, monkeypatch, first_bounce):
    """F other than diag T: M's diagonal 1 - T_ii / F_ii is kept and may be positive;
    the shortcut does not apply and the pass decides."""
    A = _transport("nonnegative")
    f = np.diag(A) * (1.2 if first_bounce == "vector" else 1.0)
    spec = f if first_bounce == "vector" else first_bounce
    T = make_store(A / (1.05 * A.sum(axis=0).max()) if first_bounce == "identity" else A,
                   tile_size=64)
    shortcut, answer, passed = _answers(monkeypatch, T, tmp_path, spec, False)
    assert not shortcut
    assert answer == passed


def test_no_pass_of_its_own_and_t_decoded_once_before_term_one(tmp_path, make_store,
                                                               monkeypatch):
    """Out of core with a nonnegative T: no "largest-M" pass, and each tile row of T is
    read once before term 1 (for the diagonal; M's rows are made from the rows kept);
    the inverse equals the one made in memory."""
    A = _transport("nonnegative")  # (pixels left out: their search reads T once more)
    T = make_store(A, tile_size=64, dtype="float32")
    reads = []
    real_read = block_csr.BlockCSR._read_row
    monkeypatch.setattr(block_csr.BlockCSR, "_read_row",
                        lambda self, i: (reads.append(int(i)), real_read(self, i))[1])
    calls = []  # apply_M's largest= of each product
    real_apply = MatVecs.apply_M

    def apply_M(self, V, largest=False):
        calls.append(largest)
        return real_apply(self, V, largest)

    monkeypatch.setattr(MatVecs, "apply_M", apply_M)
    monkeypatch.setattr(divergence.config, "SPECTRAL_RADIUS_DENSE_MAX", 16)
    ooc = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=0, in_memory=False,
                                  progress=False)
    assert ooc.spectral_method == "collatz-wielandt" and ooc.engine_path == "out-of-core"
    assert calls and not any(calls)
    assert "largest-M" not in {c.kind for c in ooc.task_costs}
    nonempty = [i for i in range(T.grid[0]) if T.tile_indptr[i + 1] > T.tile_indptr[i]]
    # terms=0 reads T for the diagonal and makes M for the bracket: each row once
    assert sorted(reads) == nonempty
    monkeypatch.undo()
    out, mem = tmp_path / "Y.zarr", tmp_path / "Z.zarr"
    bigT.stratified_inverse(T, out, terms=2, in_memory=False, progress=False)
    bigT.stratified_inverse(T, mem, terms=2, in_memory=True, progress=False)
    a, b = bigT.open(out).to_scipy(), bigT.open(mem).to_scipy()
    assert (a != b).nnz == 0


def test_kept_T_rows_are_let_go_when_the_blocks_are_not_T_tile_rows(tmp_path, make_store,
                                                                     monkeypatch):
    """Out of core, the tile rows of T read for the diagonal are kept for M's rows only
    while the run's row blocks are T's tile rows; where the tile size is chosen smaller
    (few blocks a thread), no pass would take them, and they are let go of at once
    rather than holding the cache's budget for the whole run."""
    from bigT import config
    from bigT.schedule.worker import STATE

    A = _transport("nonnegative")
    T = make_store(A, tile_size=64, dtype="float32")
    kept = []  # T's rows in the cache at each product with M
    real_apply = MatVecs.apply_M

    def apply_M(self, V, largest=False):
        kept.append(sum(len(k) == 4 and k[2] == "T" for k in list(STATE.cache._d)))
        return real_apply(self, V, largest)

    monkeypatch.setattr(MatVecs, "apply_M", apply_M)
    for blocks, out in ((16, "X.zarr"), (1024, "Y.zarr")):  # rows 32 (64 halved), 64
        monkeypatch.setattr(config, "MIN_BLOCK_ROWS", blocks)
        kept.clear()
        report = bigT.stratified_inverse(T, tmp_path / out, terms=2, in_memory=False,
                                         progress=False)
        assert report.engine_path == "out-of-core" and kept
        if blocks == 16:
            assert bigT.open(tmp_path / out).tile_size < T.tile_size
            assert set(kept) == {0}  # let go of before the first product
        else:
            assert kept[0] > 0  # kept for the first product, which takes them
