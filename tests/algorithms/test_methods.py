"""Every method against the dense formula F^-1 sum_k (I - T F^-1)^k (eq. 13), float64,
no pruning, on random diagonally dominant matrices with several tiles."""

import numpy as np
import pytest

import bigT

from inverse_helpers import dense, dense_stratified, random_dominant


@pytest.mark.parametrize("method", ["power", "horner"])
@pytest.mark.parametrize("seed", [0, 1])
def test_power_and_horner_equal_eq13(tmp_path, make_store, method, seed):
    A = random_dominant(70, seed=seed)
    T = make_store(A, tile_size=16)
    for terms in (3, 5):
        out = tmp_path / f"X{terms}.zarr"
        rep = bigT.stratified_inverse(T, out, terms=terms, prune=0, method=method,
                                      progress=False)
        assert rep.terms == terms
        np.testing.assert_allclose(dense(out), dense_stratified(A, terms), rtol=0, atol=1e-6)


@pytest.mark.parametrize("steps", [1, 2, 3])
def test_newton_schulz_equals_power_at_2j_minus_1(tmp_path, make_store, steps):
    A = random_dominant(50, seed=3)
    T = make_store(A, tile_size=16)
    held = 2**steps - 1
    rep = bigT.stratified_inverse(T, tmp_path / "NS.zarr", terms=held, prune=0,
                                  method="newton-schulz", progress=False)
    assert rep.terms == held
    rep_p = bigT.stratified_inverse(T, tmp_path / "P.zarr", terms=held, prune=0,
                                    progress=False)
    np.testing.assert_allclose(dense(tmp_path / "NS.zarr"), dense(tmp_path / "P.zarr"),
                               atol=1e-6)
    np.testing.assert_allclose(dense(tmp_path / "NS.zarr"), dense_stratified(A, held),
                               atol=1e-6)
    assert rep_p.terms == held


def test_newton_schulz_terms_round_up(tmp_path, make_store):
    A = random_dominant(40, seed=4)
    T = make_store(A, tile_size=16)
    rep = bigT.stratified_inverse(T, tmp_path / "NS.zarr", terms=4, prune=0,
                                  method="newton-schulz", progress=False)
    assert rep.terms == 7  # fewest steps j with 2^j - 1 >= 4
    assert [h.term for h in rep.history] == [0, 1, 3, 7]


def test_float32_store(tmp_path, make_store):
    A = random_dominant(48, seed=5)
    T = make_store(A, tile_size=16, dtype="float32")
    bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=4, prune=0, progress=False)
    X = bigT.open(tmp_path / "X.zarr")
    assert X.dtype == np.float32
    np.testing.assert_allclose(X.to_scipy().toarray(),
                               dense_stratified(A.astype(np.float32), 4), atol=2e-6)


def test_residual_estimate_is_unbiased_scale(tmp_path, make_store):
    from bigT.algorithms import estimate_residual, resolve_first_bounce
    from bigT.schedule.cache import TileCache
    from bigT.schedule.operators import MOperand

    A = random_dominant(120, seed=6, density=0.3)
    T = make_store(A, tile_size=32)
    bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=1, prune=0, progress=False)
    X = bigT.open(tmp_path / "X.zarr")
    exact = np.linalg.norm(np.eye(120) - A @ X.to_scipy().toarray())
    fb = resolve_first_bounce(T)
    M = MOperand(T, fb.finv, fb.active, True, TileCache(1 << 20))
    rel, absolute = estimate_residual(lambda V: M.matvec_rows(0, 120, V), lambda V: X @ V,
                                      fb, probes=256, seed=1)
    assert absolute == pytest.approx(exact, rel=0.1)
    assert rel == pytest.approx(exact / np.sqrt(120), rel=0.1)


def test_batched_right_operand_equals_whole(tmp_path, make_store, monkeypatch):
    """The memory-bounded path (right factor in batches of tile rows, output rows in
    chunks, partial sums pruned once) gives the dense result too."""
    from bigT.schedule import runner
    from bigT.schedule.memory import MemoryPlan

    A = random_dominant(80, seed=7, density=0.25)
    T = make_store(A, tile_size=16)
    # no shared factor, batches of ~2 tile rows, partial sums of a few rows per chunk
    tiny = MemoryPlan(limit=1, baseline=0, fixed_per_task=0, cache_bytes=0,
                      whole_bytes=0, work_bytes_per_task=3 * 600)
    monkeypatch.setattr(runner, "plan_memory", lambda *args: tiny)
    for method in ("power", "horner", "newton-schulz"):
        # the tiny plan cannot hold these tile rows either: the engine says so
        with pytest.warns(bigT.MemoryLimitWarning, match="may be exceeded"):
            rep = bigT.stratified_inverse(T, tmp_path / f"{method}.zarr", terms=3, prune=0,
                                          method=method, progress=False)
        np.testing.assert_allclose(dense(tmp_path / f"{method}.zarr"),
                                   dense_stratified(A, rep.terms), atol=1e-10)


def test_whole_factor_may_borrow_the_cache_share():
    """A right factor larger than its own share but within its and the cache's is held
    whole, the cache shrunk for the pass; a larger one is read in batches."""
    from bigT.schedule.cache import TileCache
    from bigT.schedule.memory import MemoryPlan
    from bigT.schedule.worker import MATVEC_BLOCKS_HELD, _block_bytes, _cache_budget, _whole_limit

    plan = MemoryPlan(limit=1, baseline=0, fixed_per_task=0, cache_bytes=1000,
                      whole_bytes=1000, work_bytes_per_task=100, threads=2)

    class Factor:
        def __init__(self, nbytes):
            self.nbytes = nbytes

    cache = TileCache(plan.cache_bytes)
    for k in range(4):
        cache.get(("T", "M", k), lambda: np.zeros(25))  # 200 bytes each
    # a mat-vec pass (no factor) may use the factor's share and half the tasks'
    assert _cache_budget(plan, None) == 1000 + 1000 + 100
    # ... less what its dense blocks take, never below nothing
    assert _cache_budget(plan, None, 600) == 1000 + 1000 + 100 - 600
    assert _cache_budget(plan, None, 5000) == 0
    assert _block_bytes(np.zeros((10, 3)), 10) == MATVEC_BLOCKS_HELD * 10 * 3 * 8
    assert _block_bytes(np.zeros(10), 10) == MATVEC_BLOCKS_HELD * 10 * 8
    assert _whole_limit(plan, Factor(900)) == 1000
    assert _cache_budget(plan, Factor(900)) == 1000
    assert _whole_limit(plan, Factor(1500)) == 1500
    cache.resize(_cache_budget(plan, Factor(1500)))
    assert cache.budget == 500 and cache.used == 400
    assert _whole_limit(plan, Factor(2500)) == 1000
    assert _cache_budget(plan, Factor(2500)) == 1000


def test_memory_limit_argument(tmp_path, make_store):
    """A limit the process can meet runs (and gives the dense result); one below what
    the process already holds is refused before anything is written, naming sizes."""
    from bigT.schedule.memory import resident_bytes

    A = random_dominant(64, seed=8)
    T = make_store(A, tile_size=16)
    enough = resident_bytes() + (256 << 20)
    bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=2, prune=0, memory_limit=enough,
                            progress=False)
    np.testing.assert_allclose(dense(tmp_path / "X.zarr"), dense_stratified(A, 2), atol=1e-10)
    with pytest.raises(bigT.MemoryLimitError, match=r"memory_limit 64 MiB is too small.*"
                       r"already holds \d+ MiB.*give at least \d+ MiB"):
        bigT.stratified_inverse(T, tmp_path / "Y.zarr", terms=2, memory_limit="64MiB",
                                progress=False)
    assert not (tmp_path / "Y.zarr").exists()




def test_at_most_one_whole_right_factor_held(tmp_path, make_store, monkeypatch):
    """Each pass lets its whole right factor go: Newton-Schulz's S (first product) is
    not still held when R (second product) is read whole."""
    import weakref

    from bigT.schedule.operators import StoreOperand

    A = random_dominant(48, seed=9)
    T = make_store(A, tile_size=16)
    seen = weakref.WeakSet()
    most = []
    original = StoreOperand.whole

    def whole(self):
        seen.add(self)
        out = original(self)
        most.append(sum(op._whole is not None for op in seen))
        return out

    monkeypatch.setattr(StoreOperand, "whole", whole)
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=3, prune=0,
                                  method="newton-schulz", progress=False)
    assert most and max(most) == 1
    np.testing.assert_allclose(dense(tmp_path / "X.zarr"), dense_stratified(A, rep.terms),
                               atol=1e-10)
