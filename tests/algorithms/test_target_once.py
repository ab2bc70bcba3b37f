"""``invert_to_target`` does its own work once: T's tile rows read once for F, the
truncation curve, the measurements and every attempt's M (no diagonal read, no
streamed product with T), in memory the engine's X measured as held (not read back
from the store), the engine's per-term residual estimate left out (the probes' errors
decide), and all of it without changing a number: the same choices, the same measured
errors and the same X, bit for bit, as the search streaming T and X. No wall-clock
assertions."""

import numpy as np
import pytest

import bigT
from bigT.algorithms import target
from bigT.algorithms.engine import InverseEngine
from bigT.algorithms.engine_path import ENVIRONMENT
from bigT.algorithms.probes import ProbedResidual
from bigT.algorithms.resident import ResidentPasses
from bigT.algorithms.run_setup import TileRows
from bigT.storage import BlockCSR

TARGET = 1 / 255


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    # rho ~0.5 at 24x32: the power form, terms the search goes past unmeasured; 6
    # tile rows
    return bigT.scenes.make("cornell", size=(24, 32), albedo=0.45, preview=False,
                            tile_size=128, path=tmp_path_factory.mktemp("once") / "T.zarr")


def _x_data(path) -> bytes:
    """X's entries, rows and columns of the term held, as bytes (bit for bit)."""
    X = bigT.open(path).to_scipy()
    X.sort_indices()
    return X.indptr.tobytes() + X.indices.tobytes() + X.data.tobytes()


def _errors(report):
    return [[(m.term, m.errors, m.truncation, m.pruning, m.clipped_errors)
             for m in a.terms] for a in report.attempts]


@pytest.mark.parametrize("in_memory", ["1", "0"])
@pytest.mark.parametrize("prune", [None, 3e-3])  # 3e-3 floors: a restart
def test_the_search_reads_T_once_and_changes_no_number(scene, tmp_path, monkeypatch,
                                                       in_memory, prune):
    T = scene.T
    monkeypatch.setenv(ENVIRONMENT, in_memory)
    # as before: T streamed, X read back from the store
    monkeypatch.setattr(target, "held_rows", lambda *args: None)
    monkeypatch.setattr(InverseEngine, "_call_on_term",
                        lambda self: self.settings.on_term(self.record))
    streamed = target.invert_to_target(T, tmp_path / "streamed.zarr", TARGET, prune=prune)
    monkeypatch.undo()
    monkeypatch.setenv(ENVIRONMENT, in_memory)

    reads, diagonals, streamed_T, opened = [], [], [], []
    real_row, real_diagonal = BlockCSR.get_tile_row, BlockCSR.diagonal
    real_stream, real_open = target.stream_matmul, target.open_store

    def counted_row(self, i, columns=None):
        if self.path == T.path:
            reads.append(int(i))
        return real_row(self, i, columns)

    def counted_diagonal(self, *args, **kwargs):
        diagonals.append(1)
        return real_diagonal(self, *args, **kwargs)

    def counted_stream(A, V, **kwargs):
        if A.path == T.path:
            streamed_T.append(V.shape)
        return real_stream(A, V, **kwargs)

    monkeypatch.setattr(BlockCSR, "get_tile_row", counted_row)
    monkeypatch.setattr(BlockCSR, "diagonal", counted_diagonal)
    def counted_open(path, *args, **kwargs):
        opened.append(path)
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr(target, "stream_matmul", counted_stream)
    monkeypatch.setattr(target, "open_store", counted_open)
    once = target.invert_to_target(T, tmp_path / "once.zarr", TARGET, prune=prune)
    monkeypatch.undo()

    if in_memory == "1":  # out of core, the engine's tasks read T's rows themselves
        assert sorted(reads) == list(range(T.grid[0])) == list(range(6))  # once, in all
        # every X measured as the engine held it, but an exhausted series' last,
        # measured after the run
        assert len(opened) == sum("exhausted" in a.ended for a in once.attempts)
    else:
        assert len(opened) == sum(len(a.terms) for a in once.attempts)
    assert not diagonals and not streamed_T
    if prune is not None:
        assert once.restarts  # the engine ran twice on the same rows
    # the same search: choices, measured errors (exactly) and X (bit for bit)
    assert (once.method, once.prune, once.prune_feed, once.prune_operator, once.terms,
            once.predicted_terms, once.restarts) == (
        streamed.method, streamed.prune, streamed.prune_feed, streamed.prune_operator,
        streamed.terms, streamed.predicted_terms, streamed.restarts)
    assert _errors(once) == _errors(streamed)
    assert _x_data(tmp_path / "once.zarr") == _x_data(tmp_path / "streamed.zarr")


def test_the_rows_product_is_the_streamed_one_bit_for_bit(scene):
    T = scene.T
    rows = TileRows(T, 2, keep=True)
    fb = target.first_bounce_of_rows(T, "diag", rows)
    V = np.random.default_rng(3).random((T.shape[0], 4))
    held = target._Products(T, fb, 2, rows=rows)
    plain = target._Products(T, fb, 2)
    try:
        a, b = held.times_T(V), plain.times_T(V)
        assert a.dtype == b.dtype == np.float64
        np.testing.assert_array_equal(a, b)
    finally:
        held.close(), plain.close()


@pytest.mark.parametrize("in_memory", ["1", "0"])
def test_no_residual_estimate_in_the_search(scene, tmp_path, monkeypatch, in_memory):
    """The engine estimates each term's residual (an M product) in a fixed run, and
    none in the search, whose probes' errors decide; the records then hold none."""
    monkeypatch.setenv(ENVIRONMENT, in_memory)
    estimates, real = [], ProbedResidual.estimate

    def counted(self, X, XZ):
        estimates.append(1)
        return real(self, X, XZ)

    probes, real_passes = [], ResidentPasses.__init__

    def passes(self, matrices, store, settings, Z, *args, **kwargs):
        probes.append(Z)  # in memory: the passes multiply their new entries by Z
        real_passes(self, matrices, store, settings, Z, *args, **kwargs)

    monkeypatch.setattr(ProbedResidual, "estimate", counted)
    monkeypatch.setattr(ResidentPasses, "__init__", passes)
    fixed = bigT.stratified_inverse(scene.T, tmp_path / "fixed.zarr", terms=2,
                                    progress=False)
    assert len(estimates) == 3 and fixed.history[-1].residual is not None
    assert [Z is not None for Z in probes] == ([True] if in_memory == "1" else [])
    estimates.clear(), probes.clear()
    report = target.invert_to_target(scene.T, tmp_path / "X.zarr", TARGET)
    assert report.met and not estimates
    assert probes == ([None] * len(report.attempts) if in_memory == "1" else [])
    assert all(h["residual"] is None for h in report.inverse["history"])
    assert bigT.open(tmp_path / "X.zarr").metadata["inverse"]["residual"] is None


def test_an_on_term_without_needs_residual_still_gets_estimates(scene, tmp_path):
    """Only a false ``needs_residual`` leaves the estimate out; ``tol`` keeps it (it
    stops on it); the X is the same either way."""
    def on_term(record):
        return None

    with_estimates = bigT.stratified_inverse(scene.T, tmp_path / "a.zarr", terms=3,
                                             progress=False, on_term=on_term)
    on_term.needs_residual = False
    without = bigT.stratified_inverse(scene.T, tmp_path / "b.zarr", terms=3,
                                      progress=False, on_term=on_term)
    with_tol = bigT.stratified_inverse(scene.T, tmp_path / "c.zarr", terms=3, tol=1e-12,
                                       progress=False, on_term=on_term)
    assert all(h.residual is not None for h in with_estimates.history)
    assert all(h.residual is None for h in without.history)
    assert all(h.residual is not None for h in with_tol.history)
    assert _x_data(tmp_path / "a.zarr") == _x_data(tmp_path / "b.zarr")


def _format1_builder():
    """tests/storage/test_row_layout.py's writer of a format-1 store (zarr alone)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).parents[1] / "storage" / "test_row_layout.py"
    spec = importlib.util.spec_from_file_location("_row_layout_builders", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module._format1_store


def test_a_format1_T_is_streamed_as_before(scene, tmp_path):
    """A format-1 T (a group per tile) is multiplied tile by tile when streamed, and
    in float32 those sums round apart from a held row's summed whole: its rows are not
    held, so the search's products stay the streamed ones, bit for bit."""
    A = scene.T.to_scipy()
    assert A.dtype == np.float32
    T1 = bigT.open(_format1_builder()(tmp_path / "v1.zarr", A, scene.T.tile_size,
                                      dtype="float32"))
    assert not T1.row_layout and target.keeps_tiles(T1, None)
    assert target.held_rows(T1, None, 2) is None
    # what holding them would change: the product of the whole rows is not the stream's
    V = np.random.default_rng(3).random((T1.shape[0], 3))
    rows = target._Products(T1, None, 2, rows=TileRows(T1, 2, keep=True))
    plain = target._Products(T1, None, 2)
    try:
        assert not np.array_equal(rows.times_T(V), plain.times_T(V))
    finally:
        rows.close(), plain.close()
    assert target.held_rows(scene.T, None, 2) is not None  # format 2: held
