"""Power loss and shared file systems (issue #33, item 6).

* Every publish is durable: a file is fsynced before the rename that publishes it, its
  directory after (the order SQLite and LMDB keep). The file system calls are recorded
  (``os.fsync`` with the path its descriptor names, and every rename) and the order
  checked against the store on disk, not against the code's own bookkeeping.
* A hidden name of a writer on another host is never deleted here.
* ``convert`` and ``scene`` are refused, in one line, while another writer holds the
  store.
"""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT import config
from bigT.atomic import _host_tag, dead_writers_siblings, hidden_sibling
from bigT.cli import main
from bigT.storage import BlockCSRWriter, from_scipy, set_redirect
from bigT.storage import open as open_store
from bigT.storage.locks import ReplaceLock, WriterLock
from bigT.storage.replace import recover_interrupted_replace

needs_proc_fds = pytest.mark.skipif(not Path("/proc/self/fd").is_dir(),
                                    reason="names a descriptor's file through /proc")
needs_flock = pytest.mark.skipif(os.name != "posix", reason="locks are no-ops without fcntl")


@dataclass(frozen=True)
class Event:
    """One recorded call: ``op`` "fsync" (``path`` the file or directory flushed,
    ``is_dir`` which) or "rename" (``path`` the source, ``dest`` the new name)."""

    op: str
    path: str
    dest: str = ""
    is_dir: bool = False


@pytest.fixture
def recorded(monkeypatch):
    """The fsyncs and renames made while the test runs, in order."""
    events: list[Event] = []
    real_fsync, real_rename, real_replace = os.fsync, os.rename, os.replace

    def fsync(fd):
        path = os.readlink(f"/proc/self/fd/{fd}")
        events.append(Event("fsync", path, is_dir=os.path.isdir(path)))
        return real_fsync(fd)

    def renaming(real):
        def rename(src, dst, *args, **kwargs):
            real(src, dst, *args, **kwargs)  # recorded once done: a failed one publishes nothing
            events.append(Event("rename", os.path.realpath(src), os.path.realpath(dst)))
        return rename

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "rename", renaming(real_rename))
    monkeypatch.setattr(os, "replace", renaming(real_replace))
    monkeypatch.setattr(config, "DURABILITY", "full")
    return events


def _index(events, predicate, what) -> int:
    found = [k for k, e in enumerate(events) if predicate(e)]
    assert found, f"no {what} in {events}"
    return found[0]


def _last(events, predicate, what) -> int:
    found = [k for k, e in enumerate(events) if predicate(e)]
    assert found, f"no {what}"
    return found[-1]


def _files_under(root: Path) -> list[Path]:
    return [Path(d, f) for d, _, files in os.walk(root) for f in files]


def _matrix(n=48, seed=0) -> sp.csr_array:
    rng = np.random.default_rng(seed)
    return sp.random_array((n, n), density=0.3, format="csr", dtype=np.float32, rng=rng)


@needs_proc_fds
def test_a_row_marker_follows_every_file_of_its_row_and_precedes_its_rename(tmp_path, recorded):
    A = _matrix()
    path = (tmp_path / "S.zarr").resolve()
    with BlockCSRWriter(path, A.shape, tile_size=16) as writer:
        for i in range(writer.grid[0]):
            r0, r1 = writer.tile_row_range(i)
            writer.write_tile_row(i, A[r0:r1])
    rows = path / "rows"
    for i in range(3):
        final = rows / str(i)
        publish = _index(recorded, lambda e: e.op == "rename" and e.dest == str(final),
                         f"rename of row {i}")
        built_in = recorded[publish].path  # the hidden .partial directory
        # the marker: a temporary file in the row renamed to its zarr.json, fsynced first
        marker = _index(recorded, lambda e: e.op == "rename"
                        and e.dest == os.path.join(built_in, "zarr.json"), "marker rename")
        marker_tmp = recorded[marker].path
        marker_fsync = _index(recorded, lambda e: e.path == marker_tmp and e.op == "fsync",
                              "marker fsync")
        flushed = {e.path: k for k, e in enumerate(recorded) if e.op == "fsync"}
        for file in _files_under(final):
            if file.name == "zarr.json" and file.parent == final:
                continue  # the marker itself
            was = str(file).replace(str(final), built_in, 1)
            assert was in flushed, f"{file} of row {i} never fsynced"
            assert flushed[was] < marker_fsync, f"{file} fsynced after row {i}'s marker"
        for folder in [Path(d) for d, _, _ in os.walk(final) if Path(d) != final]:
            was = str(folder).replace(str(final), built_in, 1)
            assert was in flushed and flushed[was] < marker_fsync, f"{folder} not fsynced"
        # the marker's name durable before the row is published, rows/ after
        assert marker_fsync < marker < _last(
            recorded[:publish], lambda e: e.op == "fsync" and e.path == built_in,
            "row directory fsync") < publish
        assert any(e.op == "fsync" and e.path == str(rows)
                   for e in recorded[publish + 1:]), f"rows/ not fsynced after row {i}"


@needs_proc_fds
def test_a_store_is_flagged_complete_after_its_index_is_durable(tmp_path, recorded):
    path = (tmp_path / "S.zarr").resolve()
    from_scipy(_matrix(), path, tile_size=16)
    # built aside, flagged complete there (its zarr.json replaced), then renamed
    publish = _last(recorded, lambda e: e.op == "rename" and e.dest == str(path), "publish")
    built_in = recorded[publish].path
    flag = _last(recorded[:publish], lambda e: e.op == "rename"
                 and e.dest == os.path.join(built_in, "zarr.json"), "completion flag")
    flushed = {e.path for e in recorded[:flag] if e.op == "fsync"}
    for name in ("tile_indptr", "tile_indices", "tile_nnz"):
        files = _files_under(path / name)
        assert files
        for file in files:
            assert str(file).replace(str(path), built_in, 1) in flushed, file
        assert os.path.join(built_in, name) in flushed  # its directory too
    # the store renamed into place, then its parent directory flushed
    assert any(e.op == "fsync" and e.is_dir and e.path == str(path.parent)
               for e in recorded[publish + 1:])
    assert open_store(path).nnz == _matrix().nnz


@needs_proc_fds
def test_a_redirect_flips_after_the_path_to_its_target_is_durable(tmp_path, recorded):
    root = (tmp_path / "V.zarr").resolve()
    from_scipy(_matrix(), root / "terms" / "t1" / "X", tile_size=16)
    recorded.clear()
    set_redirect(root, "terms/t1/X")
    flip = _last(recorded, lambda e: e.op == "rename" and e.dest == str(root / "zarr.json"),
                 "redirect flip")
    dirs = {e.path for e in recorded[:flip] if e.op == "fsync" and e.is_dir}
    assert {str(root / "terms" / "t1"), str(root / "terms"), str(root)} <= dirs
    flip_file = recorded[flip].path
    assert any(e.path == flip_file for e in recorded[:flip] if e.op == "fsync")
    assert any(e.op == "fsync" and e.path == str(root) for e in recorded[flip + 1:])
    assert open_store(root).nnz == _matrix().nnz


@needs_proc_fds
def test_durability_none_writes_the_same_store_without_an_fsync(tmp_path, recorded, monkeypatch):
    monkeypatch.setattr(config, "DURABILITY", "none")
    S = from_scipy(_matrix(), tmp_path / "S.zarr", tile_size=16)
    assert not [e for e in recorded if e.op == "fsync"]
    np.testing.assert_array_equal(S.to_scipy().toarray(), _matrix().toarray())


# --- hidden names on a shared file system ---------------------------------------------

def _dead_pid() -> int:
    """The PID of a process that has exited (reused within the test: practically never)."""
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_hidden_names_carry_the_host(tmp_path):
    name = hidden_sibling(tmp_path / "S.zarr", "partial").name
    assert name.startswith(f".S.zarr.{os.getpid()}@{_host_tag()}.") and name.endswith(".partial")


def test_another_hosts_siblings_are_never_deleted(tmp_path):
    pid = _dead_pid()
    store = tmp_path / "S.zarr"
    foreign = [tmp_path / f".S.zarr.{pid}@another-host.0123abcd.{kind}"
               for kind in ("partial", "old", "trash")]
    ours_dead = tmp_path / f".S.zarr.{pid}@{_host_tag()}.0123abcd.partial"
    old_style_dead = tmp_path / f".S.zarr.{pid}.4567cdef.trash"
    for d in [*foreign, ours_dead, old_style_dead]:
        (d / "rows").mkdir(parents=True)
    assert not dead_writers_siblings(tmp_path, "old", "S.zarr")  # the .old is foreign
    recover_interrupted_replace(store)
    assert not store.exists()  # another host's .old is never taken as ours to restore
    assert all(d.is_dir() for d in foreign)
    assert not ours_dead.exists() and not old_style_dead.exists()


def test_another_hosts_temporary_files_are_never_deleted(tmp_path):
    from bigT.atomic import remove_stale_temp_files

    pid = _dead_pid()
    foreign = tmp_path / f".zarr.json.{pid}@another-host.0123abcd.tmp"
    ours = tmp_path / f".zarr.json.{pid}@{_host_tag()}.89abcdef.tmp"
    old_style = tmp_path / f".zarr.json.{pid}.fedcba98.tmp"
    for f in (foreign, ours, old_style):
        f.write_text("{}")
    assert remove_stale_temp_files(tmp_path) == 2
    assert foreign.exists() and not ours.exists() and not old_style.exists()


# --- one writer per store ----------------------------------------------------------------

@pytest.fixture
def matrix_file(tmp_path) -> Path:
    file = tmp_path / "A.npz"
    sp.save_npz(file, sp.csr_matrix(_matrix()))
    return file


def _refused_while_held(argv, store, capsys) -> str:
    """Run ``argv`` while another process holds ``store``'s replace lock: exit 2 and
    one line on stderr, which is returned."""
    capsys.readouterr()
    with HeldElsewhere(ReplaceLock, store):
        status = main(argv)
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1 and str(store) in err, err
    return err


@needs_flock
@pytest.mark.parametrize("exists", [True, False])
def test_convert_is_refused_while_another_process_replaces_the_store(
        tmp_path, matrix_file, capsys, exists):
    S = tmp_path / "S.zarr"
    argv = ["convert", str(matrix_file), "-o", str(S), "--tile-size", "16", "--overwrite"]
    if exists:
        assert main(argv) == 0
        before = open_store(S).to_scipy().toarray()
    err = _refused_while_held(argv, S, capsys)
    assert "being written by" in err and "Traceback" not in err
    if exists:
        np.testing.assert_array_equal(open_store(S).to_scipy().toarray(), before)
    else:
        assert not S.exists()
    assert main(argv) == 0  # released: the next one runs
    assert sorted(p.name for p in tmp_path.iterdir()) == ["A.npz", "S.zarr"]


@needs_flock
def test_convert_is_refused_over_an_inverse_being_extended(tmp_path, matrix_file, capsys):
    X = tmp_path / "X.zarr"
    X.mkdir()
    with WriterLock(X, command="bigT invert (test)"):
        status = main(["convert", str(matrix_file), "-o", str(X), "--overwrite"])
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1 and "bigT invert (test)" in err, err


@needs_flock
def test_scene_overwrite_is_refused_while_another_process_replaces_the_store(tmp_path, capsys):
    S = tmp_path / "T.zarr"
    argv = ["scene", "dihedral4", "-o", str(S), "--overwrite", "--no-preview", "-q"]
    assert main(argv) == 0
    before = open_store(S).to_scipy().toarray()
    _refused_while_held(argv, S, capsys)
    np.testing.assert_array_equal(open_store(S).to_scipy().toarray(), before)


class HeldElsewhere:
    """A child process holding ``lock_class(path)`` until the block ends."""

    def __init__(self, lock_class, path: Path):
        code = (f"import sys; from bigT.storage.locks import {lock_class.__name__} as L; "
                f"lock = L({str(path)!r}, 'bigT test holder').acquire(); "
                "print('held', flush=True); sys.stdin.read()")
        self.child = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, text=True,
                                      env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})

    def __enter__(self):
        assert self.child.stdout.readline().strip() == "held"
        return self

    def __exit__(self, *exc):
        self.child.stdin.close()
        self.child.wait(timeout=60)


@needs_proc_fds
@pytest.mark.parametrize("level, fsyncs", [("none", False), ("full", True)])
def test_the_command_line_chooses_the_durability_for_its_run(
        tmp_path, matrix_file, recorded, monkeypatch, level, fsyncs):
    monkeypatch.setattr(config, "DURABILITY", "full")
    assert main(["convert", str(matrix_file), "-o", str(tmp_path / "S.zarr"), "-q",
                 "--durability", level]) == 0
    assert any(e.op == "fsync" for e in recorded) == fsyncs
    assert config.DURABILITY == "full"  # for this run only


@needs_proc_fds
@pytest.mark.parametrize("lost", ["rows group", "root zarr.json", "torn root zarr.json"])
def test_a_term_stores_header_is_left_to_finalize_and_remade_when_a_power_cut_loses_it(
        tmp_path, recorded, lost):
    """An inverse's term store is created without fsyncing its root zarr.json or its
    name (issue #30: three fsyncs fewer per store; finalize_store and the publish make
    them durable). What a power cut may then leave (the rows group or the root's
    attributes lost, or the root torn) is made anew by the next run's prepare, and the
    store it finalizes reads back whole, its root flushed before it is complete."""
    from bigT.storage import InverseStore, finalize_store, read_store_attrs, write_tile_row

    A = _matrix()
    attrs = read_store_attrs(from_scipy(A, tmp_path / "A.zarr", tile_size=16).path).replace(
        complete=False, nnz=0)
    inverse = InverseStore(tmp_path / "X.zarr")
    inverse.open_or_create({"T": "some"})
    recorded.clear()
    path = inverse.prepare_term_store(1, "X", attrs).resolve()
    # built aside: only the rows group's zarr.json and its folder flushed (bigT before
    # flushed the root's zarr.json, the folder built aside and the term's folder too)
    flushed = [Path(e.path) for e in recorded if e.op == "fsync"]
    assert len(flushed) == 2
    assert {p.name if p.name == "rows" else p.parent.name for p in flushed} == {"rows"}
    write_tile_row(path, attrs, 0, A[:16])
    if lost == "rows group":
        (path / "rows" / "zarr.json").unlink()
    elif lost == "root zarr.json":
        (path / "zarr.json").unlink()
    else:
        (path / "zarr.json").write_bytes(b"")
    assert inverse.prepare_term_store(1, "X", attrs).resolve() == path
    assert not (path / "rows" / "0").exists()  # made anew: nothing of the old kept
    for i in range(3):
        write_tile_row(path, attrs, i, A[16 * i:16 * (i + 1)])
    recorded.clear()
    X = finalize_store(path)
    flag = _last(recorded, lambda e: e.op == "rename" and e.dest == str(path / "zarr.json"),
                 "completion flag")
    assert any(e.op == "fsync" and e.path == str(path) for e in recorded[:flag])
    np.testing.assert_array_equal(X.to_scipy().toarray(), A.toarray())
    inverse.close()


@needs_proc_fds
def test_durability_none_runs_a_whole_inverse_without_an_fsync(tmp_path, recorded, monkeypatch):
    """Not only the store writers: the inverse's record (its root attributes, saved at
    the spectral radius and at each publication) follows config.DURABILITY too."""
    monkeypatch.setattr(config, "DURABILITY", "none")
    A = sp.random(40, 40, density=0.2, random_state=np.random.default_rng(3), format="csr")
    T = sp.csr_array(sp.eye(40) + 0.5 * A / A.sum(axis=0).max())  # rho(M) < 1
    S = from_scipy(T, tmp_path / "S.zarr", tile_size=16)
    report = bigT.stratified_inverse(S, tmp_path / "X.zarr", terms=2, prune=0, progress=False)
    assert report.terms == 2
    assert not [e for e in recorded if e.op == "fsync"]
