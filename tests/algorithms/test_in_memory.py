"""The series in memory (bigT.algorithms.resident) against the out-of-core path and
dense numpy: the same X (the same pruning decisions), the same records, and a store
that either path resumes, after an interruption too."""

from __future__ import annotations

import numpy as np
import pytest
from inverse_helpers import dense, dense_stratified, random_dominant

import bigT
from bigT.algorithms import engine, resident
from bigT.algorithms.engine_path import ENVIRONMENT
from bigT.errors import BigTError, DivergenceError

METHOD_OPTIONS = {
    "power": dict(prune=1e-6, prune_feed=1e-4, prune_operator=1e-4),
    "horner": dict(prune=1e-6),
    "newton-schulz": dict(prune=1e-6),
}


def both_paths(tmp_path, T, **kwargs):
    """(X in memory, X out of core, their reports) for the same call."""
    mem = bigT.stratified_inverse(T, tmp_path / "mem.zarr", in_memory=True, progress=False,
                                  **kwargs)
    ooc = bigT.stratified_inverse(T, tmp_path / "ooc.zarr", in_memory=False, progress=False,
                                  **kwargs)
    return dense(tmp_path / "mem.zarr"), dense(tmp_path / "ooc.zarr"), mem, ooc


@pytest.mark.parametrize("method", list(METHOD_OPTIONS))
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_same_inverse_as_out_of_core(tmp_path, make_store, method, dtype):
    A = random_dominant(96, seed=3, density=0.3, margin=0.8)
    T = make_store(A, tile_size=16, dtype=dtype)  # 6 tile rows out of core
    X_mem, X_ooc, mem, ooc = both_paths(tmp_path, T, terms=4, method=method,
                                        **METHOD_OPTIONS[method])
    np.testing.assert_allclose(X_mem, X_ooc, rtol=1e-6, atol=1e-6 * np.abs(X_ooc).max())
    # the same pruning decisions: the same entries at every term
    assert [(h.term, h.nnz_P, h.nnz_X) for h in mem.history] == [
        (h.term, h.nnz_P, h.nnz_X) for h in ooc.history]
    assert [h.multiply_adds for h in mem.history] == [h.multiply_adds for h in ooc.history]
    assert mem.residual == pytest.approx(ooc.residual, rel=1e-4)
    assert (mem.engine_path, ooc.engine_path) == ("in-memory", "out-of-core")
    assert {h.engine_path for h in mem.history} == {"in-memory"}
    assert {h.engine_path for h in ooc.history} == {"out-of-core"}
    assert "ran in memory" in mem.table() and "ran on local threads" in ooc.table()


@pytest.mark.parametrize("method", list(METHOD_OPTIONS))
def test_unpruned_equals_dense_series_and_approaches_inverse(tmp_path, make_store, method):
    A = random_dominant(80, seed=8, density=0.25, margin=0.5)
    T = make_store(A, tile_size=16)
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=7, prune=0.0, method=method,
                                  in_memory=True, progress=False)
    X = dense(tmp_path / "X.zarr")
    np.testing.assert_allclose(X, dense_stratified(A, rep.terms), rtol=1e-10, atol=1e-13)
    inv = np.linalg.inv(A)
    assert np.linalg.norm(X - inv) < 1e-2 * np.linalg.norm(inv)


def test_records_say_which_path(tmp_path, make_store):
    T = make_store(random_dominant(48, seed=1))
    bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=2, in_memory=True, progress=False)
    X = bigT.open(tmp_path / "X.zarr")
    assert X.metadata["inverse"]["record"]["engine_path"] == "in-memory"
    root = bigT.storage.InverseStore(tmp_path / "X.zarr").read_record()
    assert [h.details["engine_path"] for h in root.history] == ["in-memory"] * 3


@pytest.mark.parametrize("first,then", [(True, False), (False, True)])
def test_resumes_across_paths(tmp_path, make_store, first, then):
    A = random_dominant(96, seed=4, density=0.2)
    T = make_store(A, tile_size=16)
    options = dict(prune=1e-6, prune_feed=1e-5, progress=False)
    bigT.stratified_inverse(T, tmp_path / "ref.zarr", terms=5, in_memory=False, **options)
    out = tmp_path / "X.zarr"
    bigT.stratified_inverse(T, out, terms=2, in_memory=first, **options)
    rep = bigT.stratified_inverse(T, out, terms=5, in_memory=then, **options)
    assert rep.resumed_from == 2 and rep.terms == 5
    assert [h.engine_path == "in-memory" for h in rep.history] == [first] * 3 + [then] * 3
    np.testing.assert_allclose(dense(out), dense(tmp_path / "ref.zarr"), rtol=1e-6, atol=1e-9)


class Crash(Exception):
    pass


@pytest.mark.parametrize("resume_in_memory", [True, False])
def test_interrupted_in_memory_resumes_on_either_path(tmp_path, make_store, monkeypatch,
                                                       resume_in_memory):
    A = random_dominant(96, seed=5, density=0.2)
    T = make_store(A, tile_size=16)
    options = dict(prune=1e-6, progress=False)
    bigT.stratified_inverse(T, tmp_path / "ref.zarr", terms=4, in_memory=False, **options)
    monkeypatch.setattr(engine, "PUBLISH_INTERVAL_SECONDS", 0.0)  # every term published
    # the stores the in-memory run writes take T's tile size (16 here): 6 tile rows
    out = tmp_path / "X.zarr"
    writes = {"n": 0}
    real_write = resident._write_row

    def failing_write(attrs, path, block, A):
        writes["n"] += 1
        if writes["n"] == 6 + 2 * 6 + 2 * 6 + 3:  # term 0 (X), terms 1-2 (P, X), 2 more
            raise Crash("injected")
        return real_write(attrs, path, block, A)

    monkeypatch.setattr(resident, "_write_row", failing_write)
    with pytest.raises(Crash):
        bigT.stratified_inverse(T, out, terms=4, in_memory=True, **options)
    monkeypatch.setattr(resident, "_write_row", real_write)
    held = bigT.open(out)
    assert held.metadata["inverse"]["term"] == 2
    np.testing.assert_allclose(held.to_scipy().toarray(), dense_stratified(A, 2), atol=1e-5)
    rep = bigT.stratified_inverse(T, out, terms=4, in_memory=resume_in_memory, **options)
    assert rep.resumed_from == 2 and rep.terms == 4
    np.testing.assert_allclose(dense(out), dense(tmp_path / "ref.zarr"), rtol=1e-6, atol=1e-9)


def written_terms(monkeypatch) -> list[str]:
    """The term directories (``tKKKK``) of each tile row the in-memory path writes from
    now on, in order."""
    written = []
    real_write = resident._write_row

    def recording_write(attrs, path, block, A):
        written.append(path.parent.name)
        return real_write(attrs, path, block, A)

    monkeypatch.setattr(resident, "_write_row", recording_write)
    return written


def test_terms_gone_past_are_not_written(tmp_path, make_store, monkeypatch):
    A = random_dominant(96, seed=7, density=0.2)
    T = make_store(A, tile_size=16)
    options = dict(terms=4, prune=1e-6, progress=False)
    ref = bigT.stratified_inverse(T, tmp_path / "ref.zarr", in_memory=False, **options)
    written = written_terms(monkeypatch)
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", in_memory=True, **options)
    assert written == ["t0004"] * 12  # X and P, 6 tile rows each: the last term only
    # every term computed keeps its record, as out of core
    assert [(h.term, h.nnz_P, h.nnz_X) for h in rep.history] == [
        (h.term, h.nnz_P, h.nnz_X) for h in ref.history]
    assert [h.residual for h in rep.history] == pytest.approx(
        [h.residual for h in ref.history], rel=1e-4)
    stored = bigT.storage.InverseStore(tmp_path / "X.zarr").read_record()
    assert [h.term for h in stored.history] == [0, 1, 2, 3, 4]
    np.testing.assert_allclose(dense(tmp_path / "X.zarr"), dense(tmp_path / "ref.zarr"),
                               rtol=1e-6, atol=1e-9)
    # a caller reading each term gets each term published
    written.clear()
    seen = []
    bigT.stratified_inverse(T, tmp_path / "Y.zarr", in_memory=True,
                            on_term=lambda record: seen.append(
                                bigT.open(tmp_path / "Y.zarr").metadata["inverse"]["term"]),
                            **options)
    assert seen == [1, 2, 3, 4] and sorted(set(written)) == [
        "t0000", "t0001", "t0002", "t0003", "t0004"]


def test_a_term_is_published_once_the_interval_has_passed(tmp_path, make_store, monkeypatch):
    T = make_store(random_dominant(96, seed=9, density=0.2), tile_size=16)
    clock = {"now": 0.0}
    monkeypatch.setattr(engine.time, "perf_counter", lambda: clock["now"])
    real_finish = engine.InverseEngine._finish_term

    def finish_a_second_later(self, k, *args, **kwargs):
        clock["now"] += 0.4 * engine.PUBLISH_INTERVAL_SECONDS  # each term takes 0.4 of it
        return real_finish(self, k, *args, **kwargs)

    monkeypatch.setattr(engine.InverseEngine, "_finish_term", finish_a_second_later)
    written = written_terms(monkeypatch)
    bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=6, prune=1e-6, in_memory=True,
                            progress=False)
    # the interval passed before term 3 (at 1.2 of it) and again before term 6 (at 2.4):
    # terms 2 and 5 published then; term 6 is the last
    assert sorted(set(written)) == ["t0002", "t0005", "t0006"]


def test_crash_before_the_last_term_is_written_resumes(tmp_path, make_store, monkeypatch):
    A = random_dominant(96, seed=5, density=0.2)
    T = make_store(A, tile_size=16)
    options = dict(terms=4, prune=1e-6, progress=False)
    bigT.stratified_inverse(T, tmp_path / "ref.zarr", in_memory=False, **options)
    out = tmp_path / "X.zarr"

    def crash(*args):
        raise Crash("injected")

    monkeypatch.setattr(resident, "_write_row", crash)
    with pytest.raises(Crash):
        bigT.stratified_inverse(T, out, in_memory=True, **options)
    monkeypatch.undo()
    rep = bigT.stratified_inverse(T, out, in_memory=True, **options)
    assert rep.terms == 4 and [h.term for h in rep.history] == [0, 1, 2, 3, 4]
    np.testing.assert_allclose(dense(out), dense(tmp_path / "ref.zarr"), rtol=1e-6, atol=1e-9)


def test_refused_term_leaves_the_term_before_published(tmp_path, make_store, monkeypatch):
    A = random_dominant(96, seed=5, density=0.2)
    T = make_store(A, tile_size=16)
    real_refuse = engine.refuse_growing_residual

    def refuse_term_3(record, k, residual, force, store_path):
        if k == 3:
            raise DivergenceError("grew (injected)", store_path)
        return real_refuse(record, k, residual, force, store_path)

    monkeypatch.setattr(engine, "refuse_growing_residual", refuse_term_3)
    with pytest.raises(DivergenceError):
        bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=4, prune=1e-6, in_memory=True,
                                progress=False)
    held = bigT.open(tmp_path / "X.zarr")
    assert held.metadata["inverse"]["term"] == 2
    np.testing.assert_allclose(held.to_scipy().toarray(), dense_stratified(A, 2), atol=1e-5)


def test_goes_out_of_core_when_the_next_term_does_not_fit(tmp_path, make_store, monkeypatch):
    A = random_dominant(96, seed=6, density=0.2)
    T = make_store(A, tile_size=16)
    options = dict(terms=4, prune=1e-6, progress=False)
    bigT.stratified_inverse(T, tmp_path / "ref.zarr", in_memory=False, **options)
    monkeypatch.delenv(ENVIRONMENT, raising=False)  # automatic
    monkeypatch.setattr(resident.ResidentPasses, "fits",
                        lambda self, held, nnz_X, nnz_P, growth: held < 2)
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", **options)
    assert [h.engine_path for h in rep.history] == ["in-memory"] * 3 + ["out-of-core"] * 2
    assert rep.engine_path == "out-of-core" and "out of core from term 3" in rep.engine_path_reason
    np.testing.assert_allclose(dense(tmp_path / "X.zarr"), dense(tmp_path / "ref.zarr"),
                               rtol=1e-6, atol=1e-9)


def test_automatic_choice_and_its_overrides(tmp_path, make_store, monkeypatch):
    T = make_store(random_dominant(48, seed=2))
    monkeypatch.delenv(ENVIRONMENT, raising=False)
    auto = bigT.stratified_inverse(T, tmp_path / "a.zarr", terms=1, progress=False)
    assert auto.engine_path == "in-memory" and "may hold" in auto.engine_path_reason
    monkeypatch.setenv(ENVIRONMENT, "0")
    env = bigT.stratified_inverse(T, tmp_path / "b.zarr", terms=1, progress=False)
    assert env.engine_path == "out-of-core" and ENVIRONMENT in env.engine_path_reason
    asked = bigT.stratified_inverse(T, tmp_path / "c.zarr", terms=1, in_memory=True,
                                    progress=False)
    assert asked.engine_path == "in-memory"  # the argument wins over the environment
    monkeypatch.setenv(ENVIRONMENT, "sometimes")
    with pytest.raises(BigTError, match=ENVIRONMENT):
        bigT.stratified_inverse(T, tmp_path / "d.zarr", terms=1, progress=False)
    with pytest.raises(BigTError, match="in_memory"):
        bigT.stratified_inverse(T, tmp_path / "e.zarr", terms=1, in_memory="yes",
                                progress=False)


def test_exhausted_series_in_memory(tmp_path, make_store):
    d = 0.5 + np.linspace(0, 1, 40)
    T = make_store(np.diag(d), tile_size=16)
    rep = bigT.stratified_inverse(T, tmp_path / "X.zarr", terms=5, in_memory=True,
                                  progress=False)
    assert rep.terms == 5 and "exhausted" in rep.stopped and rep.products == 0
    np.testing.assert_array_equal(dense(tmp_path / "X.zarr"), np.diag(1 / d))


@pytest.mark.parametrize("method", ["power", "horner"])
def test_colour_general_path_same_as_out_of_core(tmp_path, method):
    from test_colour_inverse import colour_transport, dense_colour_stratified, read, store

    A = colour_transport(4, 6)  # per-pixel camera mixing: the general colour engine
    T = store(tmp_path, A, (4, 6))
    options = dict(terms=3, prune=0.0, method=method, colour_path="general", progress=False)
    mem = bigT.stratified_inverse(T, tmp_path / "mem.zarr", in_memory=True, **options)
    bigT.stratified_inverse(T, tmp_path / "ooc.zarr", in_memory=False, **options)
    assert mem.engine_path == "in-memory"
    X_mem, X_ooc = read(tmp_path / "mem.zarr"), read(tmp_path / "ooc.zarr")
    np.testing.assert_allclose(X_mem, X_ooc, rtol=1e-6, atol=1e-12 * np.abs(X_ooc).max())
    want = dense_colour_stratified(A, 3)
    np.testing.assert_allclose(X_mem, want, rtol=0, atol=1e-10 * np.abs(want).max())


def test_products_on_few_columns_same_as_out_of_core(tmp_path, make_store, monkeypatch):
    """T lit on a third of its patches (the dense corner's shape: most rows and columns
    empty) through the numba kernels: the in-memory products run on the right factor's
    narrowed columns (bigT.kernels.row_ranges.narrow_columns) and give the out-of-core
    path's X and entries."""
    from bigT import config

    monkeypatch.setattr(config, "KERNEL_NUMPY_MAX_WORK", 0)  # the kernels, not numpy
    lit = np.sort(np.random.default_rng(4).choice(120, 40, replace=False))
    A = np.zeros((120, 120))
    A[np.ix_(lit, lit)] = random_dominant(40, seed=5, density=0.4, margin=0.8)
    narrowed = []
    real = resident.narrow_columns
    monkeypatch.setattr(resident, "narrow_columns",
                        lambda B, t: narrowed.append(real(B, t)) or narrowed[-1])
    T = make_store(A, tile_size=16)
    X_mem, X_ooc, mem, ooc = both_paths(tmp_path, T, terms=4, method="power",
                                        **METHOD_OPTIONS["power"])
    assert any(nc is not None for nc in narrowed)
    np.testing.assert_allclose(X_mem, X_ooc, rtol=1e-6, atol=1e-6 * np.abs(X_ooc).max())
    assert [(h.term, h.nnz_P, h.nnz_X) for h in mem.history] == [
        (h.term, h.nnz_P, h.nnz_X) for h in ooc.history]
    np.testing.assert_allclose(X_mem[np.ix_(lit, lit)],
                               np.linalg.inv(A[np.ix_(lit, lit)]), atol=0.05)


def _counting(monkeypatch, module, name: str) -> list:
    """Calls of ``module.name`` recorded (its first argument) while the test runs."""
    calls, real = [], getattr(module, name)

    def counted(*args, **kwargs):
        calls.append(args[0] if args else None)
        return real(*args, **kwargs)

    monkeypatch.setattr(module, name, counted)
    return calls


def test_a_second_small_run_starts_no_thread(tmp_path, make_store, monkeypatch):
    """Issue #30's fixed costs: the run's pools (T's rows, M, the writes, the term
    ahead) are the process's, started by the first run, not by each (bigT before
    started five threads for every run of this size, ~3 ms each under load)."""
    import threading

    A = random_dominant(96, seed=5, density=0.3, margin=0.8)
    T = make_store(A, tile_size=32)
    kwargs = dict(terms=5, prune=1e-6, in_memory=True, progress=False)
    first = bigT.stratified_inverse(T, tmp_path / "a.zarr", **kwargs)
    starts = _counting(monkeypatch, threading.Thread, "start")
    again = bigT.stratified_inverse(T, tmp_path / "b.zarr", **kwargs)
    assert [t.name for t in starts] == []
    assert np.array_equal(dense(tmp_path / "a.zarr"), dense(tmp_path / "b.zarr"))
    assert [h.nnz_X for h in again.history] == [h.nnz_X for h in first.history]


def test_publishing_replaces_the_root_once_and_stays_durable(tmp_path, make_store,
                                                             monkeypatch):
    """The flip and the record are one durable replace of the root's zarr.json (bigT
    before wrote it twice, four fsyncs): the published term's files are fsynced before
    it, the root after it, and the store reopens at the term recorded."""
    import os

    A = random_dominant(64, seed=6, density=0.3, margin=0.8)
    T = make_store(A, tile_size=32)
    out = tmp_path / "X.zarr"
    events: list[tuple[str, str]] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        return real_fsync(fd)

    def replace(src, dst, *args, **kwargs):
        events.append(("replace", os.fspath(dst)))
        return real_replace(src, dst, *args, **kwargs)

    if not os.path.isdir("/proc/self/fd"):
        pytest.skip("names a descriptor's file through /proc")
    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    report = bigT.stratified_inverse(T, out, terms=3, prune=1e-6, in_memory=True,
                                     progress=False)
    root_json = str(out / "zarr.json")
    root_writes = [i for i, e in enumerate(events) if e == ("replace", root_json)]
    flips = [i for i in root_writes if i > max(
        j for j, (op, p) in enumerate(events) if op == "fsync" and "/t0" in p)]
    assert len(flips) == 1  # after the term's files, the root written once
    assert ("fsync", str(out)) in events[flips[0] + 1:]  # the rename made durable
    monkeypatch.undo()
    reopened = bigT.open(out)
    assert reopened.metadata["inverse"]["dir"] == report.terms
    np.testing.assert_array_equal(reopened.to_scipy().toarray(), dense(out))


def test_a_small_run_fsyncs_what_publishing_needs_once(tmp_path, make_store, monkeypatch):
    """A run of one tile row that publishes only its last term: its first record is
    saved with the tile size (one write, not two), X records its term with its
    completion flag (not rewritten when published), its stores' headers are made
    durable by their completion and the publish (not each on its own) and the flip
    carries the record. bigT before made 86 fsyncs here and replaced the root's zarr.json 5 times. The
    store reopens at the last term, equal bit for bit to one whose every term was
    published."""
    import os

    A = random_dominant(48, seed=7, density=0.3, margin=0.8)
    T = make_store(A, tile_size=64)
    out = tmp_path / "X.zarr"
    monkeypatch.setattr(engine, "PUBLISH_INTERVAL_SECONDS", 1e9)  # the last term only
    fsyncs = _counting(monkeypatch, os, "fsync")
    real_replace, root_writes = os.replace, []

    def replace(src, dst, *args, **kwargs):
        if os.fspath(dst) == os.fspath(out / "zarr.json"):
            root_writes.append(src)
        return real_replace(src, dst, *args, **kwargs)

    monkeypatch.setattr(os, "replace", replace)
    report = bigT.stratified_inverse(T, out, terms=5, prune=1e-6, in_memory=True,
                                     progress=False)
    monkeypatch.undo()
    assert len(fsyncs) <= 76
    assert len(root_writes) <= 3  # created (with the tile size), spectral radius, flip
    assert bigT.open(out).metadata["inverse"]["term"] == report.terms
    monkeypatch.setattr(engine, "PUBLISH_INTERVAL_SECONDS", 0.0)  # every term
    every = bigT.stratified_inverse(T, tmp_path / "every.zarr", terms=5, prune=1e-6,
                                    in_memory=True, progress=False)
    assert every.terms == report.terms
    assert np.array_equal(dense(out), dense(tmp_path / "every.zarr"))


def test_M_written_in_place_is_the_stacked_blocks(tmp_path, make_store, monkeypatch):
    """A grey M with F = diag T is written straight into its arrays
    (bigT.kernels.row_ranges.scaled_off_diagonal_rows), not made block by block and
    stacked: the same M and the same X, bit for bit, as the blocks' path."""
    from bigT import config

    monkeypatch.setattr(config, "KERNEL_NUMPY_MAX_WORK", 0)  # the kernels, not numpy
    A = random_dominant(96, seed=6, density=0.3, margin=0.8)
    T = make_store(A, tile_size=16)
    made, real = [], resident.ResidentMatrices._make_M
    monkeypatch.setattr(resident.ResidentMatrices, "_make_M",
                        lambda self: made.append(real(self)) or made[-1])
    kwargs = dict(terms=3, in_memory=True, progress=False, **METHOD_OPTIONS["power"])
    bigT.stratified_inverse(T, tmp_path / "a.zarr", **kwargs)
    written = _counting(monkeypatch, resident, "scaled_off_diagonal_rows")
    monkeypatch.setattr(resident, "scaled_off_diagonal_rows", lambda *args: None)
    bigT.stratified_inverse(T, tmp_path / "b.zarr", **kwargs)
    assert written == []  # the second run made M block by block
    fast, stacked = made
    assert fast.has_canonical_format
    for name in ("indptr", "indices", "data"):
        assert np.array_equal(getattr(fast, name), getattr(stacked, name)[:fast.indptr[-1]
                                                                           if name != "indptr" else None])
    assert np.array_equal(dense(tmp_path / "a.zarr"), dense(tmp_path / "b.zarr"))


def test_terms_gone_past_in_memory_clean_and_trim_nothing(tmp_path, make_store, monkeypatch):
    """A small run in memory scans its store for terms to delete at term 0 and at its
    end only (a term it goes past writes nothing; a published one is cleaned after),
    and hands no heap pages back (bigT before did both before every term: 7 scans
    and 7 ``malloc_trim`` at n = 1000, issue #30); a term directory a crash left is
    still gone when the run ends, and out of core every term still cleans."""
    from bigT.storage import InverseStore

    A = random_dominant(96, seed=4, density=0.2)
    T = make_store(A, tile_size=16)
    options = dict(terms=2, prune=1e-6, progress=False, in_memory=True)
    bigT.stratified_inverse(T, tmp_path / "X.zarr", **options)
    (tmp_path / "X.zarr" / "t0009" / "X").mkdir(parents=True)  # a crashed run's litter
    cleans = _counting(monkeypatch, InverseStore, "clean")
    trims = _counting(monkeypatch, engine, "return_freed_memory")
    monkeypatch.setattr(engine, "PUBLISH_INTERVAL_SECONDS", 1e9)  # the last term only
    bigT.stratified_inverse(T, tmp_path / "X.zarr", **{**options, "terms": 6})
    assert (len(cleans), len(trims)) == (2, 0)  # resumed: before term 3, at the end
    assert not (tmp_path / "X.zarr" / "t0009").exists()
    cleans.clear()
    bigT.stratified_inverse(T, tmp_path / "Y.zarr", **{**options, "terms": 4})
    assert len(cleans) == 2  # term 0 and the end
    monkeypatch.setattr(engine, "TRIM_MIN_BYTES", 0)  # matrices this size or more
    bigT.stratified_inverse(T, tmp_path / "Z.zarr", **{**options, "terms": 4})
    assert len(trims) == 4  # before terms 1-4
    cleans.clear()
    bigT.stratified_inverse(T, tmp_path / "W.zarr", **{**options, "terms": 4,
                                                          "in_memory": False})
    assert len(cleans) == 6  # term 0, before terms 1-4, the end
