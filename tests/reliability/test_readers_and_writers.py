"""Readers of an inverse being extended, and a second writer (issue #17, item 4)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parents[1] / "algorithms"))

from inverse_helpers import random_dominant, store  # noqa: E402

from bigT import stratified_inverse as invert  # noqa: E402
from bigT.cli import main  # noqa: E402
from bigT.errors import IncompleteStoreError  # noqa: E402
from bigT.storage import open as open_store  # noqa: E402
from bigT.storage.inverse_store import InverseStore  # noqa: E402
from bigT.storage.locks import WriterLock  # noqa: E402

needs_flock = pytest.mark.skipif(os.name != "posix", reason="locks are no-ops without fcntl")


@pytest.fixture
def T(tmp_path):
    return store(tmp_path, random_dominant(64, seed=5), "T.zarr", tile_size=16)


def terms_on_disk(X: Path) -> list[str]:
    return sorted(p.name for p in X.iterdir() if p.name.startswith("t"))


@needs_flock
def test_a_reader_keeps_the_term_it_opened_while_the_writer_moves_on(T, tmp_path):
    X = tmp_path / "X.zarr"
    invert(T, X, terms=1, progress=False)
    reader = open_store(X)
    before = reader.to_scipy().toarray()
    invert(T, X, terms=3, progress=False)  # drops term 1's P, keeps its X for the reader
    assert reader.path.parent.name == "t0001" and reader.path.is_dir()
    np.testing.assert_array_equal(reader.to_scipy().toarray(), before)
    assert open_store(X).metadata["inverse"]["term"] == 3  # a new reader sees term 3
    del reader
    invert(T, X, terms=3, progress=False)  # held already: only cleans
    assert terms_on_disk(X) == ["t0003"]


@needs_flock
def test_without_readers_only_the_current_term_stays(T, tmp_path):
    X = tmp_path / "X.zarr"
    invert(T, X, terms=3, progress=False)
    assert terms_on_disk(X) == ["t0003"]


def test_dropped_terms_are_deleted_in_the_background_and_waited_for(T, tmp_path,
                                                                    monkeypatch):
    """Each superseded term is renamed away at once and deleted by a thread while the
    next term computes; the run returns only when every deletion has finished."""
    import threading

    from bigT.storage import locks

    started = []
    real_start = threading.Thread.start

    def start(thread):
        if thread.name.startswith("bigT-remove-"):
            started.append(thread)
        real_start(thread)

    monkeypatch.setattr(threading.Thread, "start", start)
    X = tmp_path / "X.zarr"
    invert(T, X, terms=3, progress=False)
    assert len(started) == 3 and not any(t.is_alive() for t in started)
    assert terms_on_disk(X) == ["t0003"]
    assert not [p.name for p in X.iterdir() if p.name.endswith(".trash")]
    monkeypatch.setattr(locks.config, "BACKGROUND_REMOVAL", False)
    invert(T, X, terms=4, progress=False)
    assert len(started) == 3 and terms_on_disk(X) == ["t0004"]


@needs_flock
def test_a_second_writer_is_refused_with_the_first_ones_pid(T, tmp_path, capsys):
    X = tmp_path / "X.zarr"
    invert(T, X, terms=1, progress=False)
    before = open_store(X).to_scipy().toarray()
    with WriterLock(X, command="bigT invert (test)"):
        status = main(["invert", str(T.path), "-o", str(X), "--terms", "2", "-q"])
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1
    assert f"PID {os.getpid()}" in err and str(X) in err and "Traceback" not in err
    np.testing.assert_array_equal(open_store(X).to_scipy().toarray(), before)
    assert main(["invert", str(T.path), "-o", str(X), "--terms", "2", "-q"]) == 0


def test_an_inverse_before_its_first_term_says_so(tmp_path):
    X = tmp_path / "X.zarr"
    store = InverseStore(X)
    store.open_or_create({"T": "some"})
    store.close()
    with pytest.raises(IncompleteStoreError, match="first term is not finished"):
        open_store(X)


@needs_flock
def test_a_reader_whose_term_is_deleted_before_its_lease_opens_the_new_term(T, tmp_path,
                                                                            monkeypatch):
    """The race the lease cannot close alone: the reader resolved the redirect to term 1,
    then the writer moved on and deleted term 1 before the reader took its lease."""
    from bigT.storage import block_csr

    X = tmp_path / "X.zarr"
    invert(T, X, terms=1, progress=False)
    real_lease = block_csr.ReaderLease
    raced = []

    def lease_after_the_writer_moved_on(store):
        if not raced and Path(store).parent.name.startswith("t0"):  # a term, not the root
            raced.append(Path(store))
            invert(T, X, terms=2, progress=False)  # publishes term 2, deletes term 1
        return real_lease(store)

    monkeypatch.setattr(block_csr, "ReaderLease", lease_after_the_writer_moved_on)
    reader = open_store(X)
    assert raced[0].parent.name == "t0001" and not raced[0].exists()
    assert reader.metadata["inverse"]["term"] == 2


def test_a_refused_run_lets_go_of_the_writer_lock(T, tmp_path):
    from bigT.errors import StoreError

    X = tmp_path / "X.zarr"
    invert(T, X, terms=1, prune=1e-5, progress=False)
    with pytest.raises(StoreError, match="different prune") as refused:
        invert(T, X, terms=1, prune=1e-4, progress=False)
    # the traceback (and its frames) still alive: the lock must not be
    assert refused.value is not None
    report = invert(T, X, terms=1, prune=1e-4, progress=False, overwrite=True)
    assert report.terms == 1
