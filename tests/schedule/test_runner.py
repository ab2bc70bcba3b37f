"""The schedule layer: pass descriptions that pickle, one task per row block on the
threaded runner, mat-vecs, zero tile pairs never read, the tile cache, row blocks
finer than T's tiles, and the same result on an in-process distributed.Client."""

import pickle
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT.algorithms.methods import power_task
from bigT.algorithms.run_setup import choose_tile_size
from bigT.schedule import matvec as mv
from bigT.schedule.cache import TileCache
from bigT.schedule.operators import StoreOperand
from bigT.schedule.runner import ThreadRunner, new_pass_id
from bigT.schedule.spec import BlockStats, MemoryPolicy, PassSpec, RowBlock, row_blocks
from bigT.storage import from_scipy


def _dominant(n, seed, density=0.2):
    rng = np.random.default_rng(seed)
    A = sp.random(n, n, density=density, random_state=rng).toarray()
    np.fill_diagonal(A, 0)
    A *= 0.5 / max(A.sum(0).max(), A.sum(1).max())
    return A + np.eye(n)


def _dense_eq13(T, n):
    Finv = np.diag(1 / np.diag(T))
    M = np.eye(len(T)) - T @ Finv
    return Finv @ sum(np.linalg.matrix_power(M, k) for k in range(n + 1))


def test_pass_description_round_trips_through_pickle():
    spec = PassSpec(op="power", term=3, task=power_task, T="/data/T.zarr", first_bounce="ab12",
                    zero_diagonal=True, n=100, block_rows=16, dtype="float32",
                    memory=MemoryPolicy(2 << 30, 2, 100, 5000),
                    inputs=(("P", "/data/X.zarr/t0002/P"), ("X", "/data/X.zarr/t0002/X")),
                    outputs=(("P", "/data/X.zarr/t0003/P"),), right="P", threshold=1e-5,
                    pass_id=new_pass_id())
    back = pickle.loads(pickle.dumps(spec))
    assert back == spec and back.task is power_task
    assert back.input_path("X").endswith("t0002/X") and back.output_path("P").endswith("P")
    assert len(pickle.dumps(spec)) < 2000  # a graph carries paths, never data
    stats = BlockStats(4, 1.5, "1@h", nnz_P=3, y=np.ones((2, 1)))
    assert pickle.loads(pickle.dumps(stats)).nnz_P == 3
    assert row_blocks(100, 16)[-1] == RowBlock(6, 96, 100)
    assert [b.index for b in row_blocks(100, 16, [2, 5])] == [2, 5]


def test_row_blocks_split_coarse_tiles():
    # 196608 rows in 8192-row tiles: 24 blocks, enough for 2 threads; 49152 rows: split
    assert choose_tile_size(196608, 8192, 2) == 8192
    assert choose_tile_size(49152, 8192, 2) == 4096
    assert choose_tile_size(49152, 8192, 8) == 1024  # not below MIN_BLOCK_ROWS
    assert choose_tile_size(100, 16, 2) == 16
    assert choose_tile_size(768, 8192, 2) == 8192  # one block either way: no halving


def test_threaded_matvec_equals_dense(tmp_path):
    A = _dominant(50, 1)
    S = from_scipy(sp.csr_array(A), tmp_path / "A.zarr", tile_size=16, dtype="float64")
    V = np.random.default_rng(0).standard_normal((50, 3))
    spec = mv.matvec_spec("mv", str(S.path), 50, 16, "float64")
    Y = mv.matvec(ThreadRunner(2), spec, V)
    np.testing.assert_allclose(Y, A @ V, atol=1e-12)


def test_zero_tile_pairs_are_never_read(tmp_path, monkeypatch):
    # block-diagonal T: tile pairs across blocks are zero, and the second block has
    # no interreflection, so P's tile rows there are empty from term 1 on
    A = np.zeros((64, 64))
    A[:32, :32] = _dominant(32, 2, density=0.5)
    A[32:, 32:] = np.diag(1 + np.arange(32) / 32)
    T = from_scipy(sp.csr_array(A), tmp_path / "T.zarr", tile_size=16, dtype="float64")
    reads = []
    orig = StoreOperand._read_row

    def row(self, j):
        r = orig(self, j)
        reads.append((str(self.store.path), int(j), r.nnz))
        return r

    monkeypatch.setattr(StoreOperand, "_read_row", row)
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=3, prune=0, progress=False)
    P_reads = [r for r in reads if r[0].endswith("/P")]
    assert P_reads and all(nnz > 0 for _, _, nnz in P_reads)
    assert {j for _, j, _ in P_reads} <= {0, 1}
    np.testing.assert_allclose(bigT.open(tmp_path / "X.zarr").to_scipy().toarray(),
                               _dense_eq13(A, 3), atol=1e-12)
    assert rep.history[-1].tiles_computed == 4


def test_row_blocks_finer_than_T_tiles_give_the_same_inverse(tmp_path, monkeypatch):
    """The term stores may have a smaller tile size than T (more tasks): M's rows
    then come from slices of T's tile rows; the inverse is the same."""
    from bigT import config

    A = _dominant(96, 5, density=0.3)
    T = from_scipy(sp.csr_array(A), tmp_path / "T.zarr", tile_size=32, dtype="float64")
    monkeypatch.setattr(config, "MIN_BLOCK_ROWS", 8)
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=3, prune=0, progress=False,
                                  method="horner")
    X = bigT.open(tmp_path / "X.zarr")
    assert rep.tile_size == X.tile_size == 8  # 96 rows, 2 threads: >= 8 blocks wanted
    np.testing.assert_allclose(X.to_scipy().toarray(), _dense_eq13(A, 3), atol=1e-12)


def test_tile_cache_bounded_and_scan_resistant():
    """Admitted while they fit, kept until dropped: a second scan of the same rows hits
    the first ones (an LRU smaller than the scan would hit none)."""
    c = TileCache(1000)
    for _ in range(2):
        for k in range(20):
            c.get(("p", "row", k), lambda: np.zeros(30))  # 240 bytes each
    assert c.used == 4 * 240
    assert (c.hits, c.misses) == (4, 36)
    c.get(("q", "row", 0), lambda: np.zeros(1))
    c.drop_where(lambda path: path != "q")
    assert c.used == 8
    misses = c.misses
    for k in range(3):
        c.get(("p", "row", k), lambda: np.zeros(30))
    assert c.misses == misses + 3  # dropped entries are recomputed
    c.resize(500)  # the last admitted go first
    assert c.used == 8 + 2 * 240
    c.get(("p", "row", 0), lambda: None)
    c.get(("p", "row", 2), lambda: np.zeros(30))
    assert c.misses == misses + 4


def test_in_process_client_same_result(tmp_path):
    distributed = pytest.importorskip("distributed")
    A = _dominant(48, 3)
    T = from_scipy(sp.csr_array(A), tmp_path / "T.zarr", tile_size=16, dtype="float64")
    bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=3, prune=1e-8, progress=False)
    with distributed.Client(processes=False, n_workers=1, threads_per_worker=2,
                            dashboard_address=None) as client:
        rep = bigT.stratified_inverse(T, tmp_path / "Y.zarr", terms=3, prune=1e-8,
                                      progress=False, scheduler=client)
    assert rep.scheduler.startswith("dask cluster")
    X = bigT.open(tmp_path / "X.zarr").to_scipy().toarray()
    Y = bigT.open(tmp_path / "Y.zarr").to_scipy().toarray()
    np.testing.assert_array_equal(X, Y)


def test_in_memory_stores_and_unserved_urls_are_refused(tmp_path):
    from bigT.schedule.runner import worker_path
    from bigT.storage import ObjectPath

    A = _dominant(16, 4)
    T = from_scipy(sp.csr_array(A), tmp_path / "T.zarr", tile_size=16, dtype="float64")
    with pytest.raises(bigT.StoreError, match="not served"):
        bigT.stratified_inverse(T, "ftp://host/X.zarr", terms=1, progress=False)
    with pytest.raises(bigT.StoreError, match="in-memory"):
        bigT.stratified_inverse(T, {"zarr.json": b""}, terms=1, progress=False)
    # a URL of object storage goes to the workers as itself, a path made absolute
    assert isinstance(worker_path("s3://bucket/X.zarr"), ObjectPath)
    assert worker_path("X.zarr") == str(Path("X.zarr").resolve())


def test_a_rerun_task_whose_rows_are_written_recomputes_nothing(tmp_path):
    """A scheduler reruns a task whose worker died after writing: the rows on disk
    stand, the task function is not called, the counts come from the row markers."""
    from bigT.schedule.worker import run_block
    from bigT.storage import StoreAttrs, create_store, read_store_attrs, write_tile_row

    A = sp.csr_array(_dominant(32, 6))
    outputs = []
    for name in ("P", "X"):
        path = tmp_path / name
        create_store(path, StoreAttrs((32, 32), 16, "float64"))
        write_tile_row(path, read_store_attrs(path), 1, A[16:32])
        outputs.append((name, str(path)))

    def must_not_run(ctx):
        raise AssertionError("recomputed")

    spec = PassSpec(op="power", term=2, task=must_not_run, T=str(tmp_path / "T"),
                    first_bounce="", zero_diagonal=True, n=32, block_rows=16,
                    dtype="float64", memory=MemoryPolicy(None, 1, 32, 0),
                    outputs=tuple(outputs), pass_id="p")
    stats = run_block(spec, RowBlock(1, 16, 32), {})
    assert (stats.nnz_P, stats.nnz_X) == (A[16:32].nnz, A[16:32].nnz)
    with pytest.raises(bigT.BigTError, match="rows 0:16.*recomputed"):
        run_block(spec, RowBlock(0, 0, 16), {})  # row 0 is not written: the task runs


def test_a_failed_pass_returns_only_after_its_other_tasks(monkeypatch):
    """dask raises at the first failing task; the runner waits for the tasks still
    running, so none of them writes into a store after the caller went on (to clean
    it, or to resume it)."""
    import threading
    import time

    from bigT.schedule import runner as runner_module

    finished = []
    started = threading.Barrier(2, timeout=5)

    def fake_run_block(spec, block, shared):
        started.wait()  # both tasks run at once
        if block.index == 0:
            raise RuntimeError("task 0 failed")
        time.sleep(0.3)
        finished.append(block.index)
        return block.index

    monkeypatch.setattr(runner_module, "run_block", fake_run_block)
    spec = PassSpec(op="test", term=0, task=None, T="", first_bounce="", zero_diagonal=(),
                    n=2, block_rows=1, dtype="float64", memory=None)
    with pytest.raises(RuntimeError, match="task 0 failed"):
        ThreadRunner(2).map(spec, row_blocks(2, 1), {})
    assert finished == [1]


def test_every_task_gets_the_pass_inputs_themselves_and_the_bar_counts_blocks(monkeypatch):
    """The spec and the shared arrays go into the graph once, untraversed: each task
    receives those very objects (not copies dask rebuilt), and the progress bar advances
    once per block, not for the two input nodes."""
    from bigT.schedule import runner as runner_module

    seen, ticks = [], []

    class Bar:
        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def update(self, n=1):
            ticks.append(n)

    def fake_run_block(spec, block, shared):
        seen.append((spec, shared))
        return block.index

    monkeypatch.setattr(runner_module, "run_block", fake_run_block)
    monkeypatch.setattr(runner_module, "_bar", lambda *a, **k: Bar())
    monkeypatch.setattr(runner_module.CostLedger, "record", lambda *a, **k: None)
    spec = PassSpec(op="test", term=0, task=None, T="", first_bounce="", zero_diagonal=(),
                    n=5, block_rows=1, dtype="float64", memory=None)
    shared = {"V": np.arange(5.0)}
    assert ThreadRunner(2).map(spec, row_blocks(5, 1), shared) == [0, 1, 2, 3, 4]
    assert len(seen) == 5 and all(s is spec and sh is shared for s, sh in seen)
    assert sum(ticks) == 5
