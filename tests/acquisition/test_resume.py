"""An interrupted ``bigT acquire build`` resumes with the tile rows it had not written and
gives the same T as an uninterrupted build; tile rows finished before the interruption
are kept as they are (not rewritten); an interrupted build of other captures or
settings is not resumed but refused, unless ``--overwrite``; Ctrl-C is exit status 130;
a build killed outright (SIGKILL) resumes too; a capture retaken in the same folder
(same name, other content) is another capture: no resume.

T is 192 x 192 (a 12x16 grid of 2x2 super-pixels) in tiles of 32: six tile rows. A
memory budget of 4 KiB lets each pass over the captures fill a single tile row, so the
build takes six passes and can be cut between any two.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import bigT.storage.writer
from bigT import scenes
from bigT.acquisition import build_transport
from bigT.cli import main
from bigT.errors import IncompleteStoreError, StoreError
from bigT.storage import BlockCSRWriter
from bigT.storage import open as open_store
from bigT.storage import completed_rows, read_store_attrs

# 4 KiB is under what one tile row holds, by design: each pass warns of it once
pytestmark = pytest.mark.filterwarnings("ignore::bigT.errors.MemoryLimitWarning")

TILE = 32
ROWS = 6  # 192 / 32
BUDGET = 4096
SETS = ("brute-force", "stripes")


@pytest.fixture(scope="module")
def rig(tmp_path_factory) -> Path:
    """Patterns and captures of both methods, captures of the brute-force patterns with
    another noise seed ("other"), and T built whole from each."""
    root = tmp_path_factory.mktemp("rig")
    scenes.make("corner", (12, 16), root / "scene.zarr", density="exact", preview=False,
                progress=False)
    simulate = ["--camera", "30x40", "--noise", "0.001", "--black", "0.02", "-q"]
    for method in SETS:
        assert main(["acquire", "patterns", "--method", method, "--projector", "24x32",
                     "--superpixel", "2", "-o", str(root / f"{method}-patterns"), "-q"]) == 0
        assert main(["acquire", "simulate", str(root / "scene.zarr"),
                     str(root / f"{method}-patterns"), "-o",
                     str(root / f"{method}-captures"), *simulate]) == 0
    assert main(["acquire", "simulate", str(root / "scene.zarr"),
                 str(root / "brute-force-patterns"), "-o", str(root / "other-captures"),
                 "--seed", "1", *simulate]) == 0
    for name, patterns in (("brute-force", "brute-force"), ("stripes", "stripes"),
                           ("other", "brute-force")):
        report = build_transport(root / f"{patterns}-patterns", root / f"{name}-captures",
                                 root / f"{name}-whole.zarr", tile_size=TILE,
                                 memory_bytes=BUDGET if name == "brute-force" else None,
                                 progress=False)
        if name == "brute-force":
            assert report.passes == ROWS  # one tile row per pass: any pass can be cut
    return root


@pytest.fixture
def work(rig, tmp_path) -> Path:
    for name in ("brute-force", "stripes"):
        shutil.copytree(rig / f"{name}-patterns", tmp_path / f"{name}-patterns")
    for name in ("brute-force", "stripes", "other"):
        shutil.copytree(rig / f"{name}-captures", tmp_path / f"{name}-captures")
    return tmp_path


def _dense(path) -> np.ndarray:
    return open_store(path).to_scipy().toarray()


def _row_prints(store: Path, rows) -> dict:
    """Inode, modification time and bytes of every file of the given tile rows."""
    prints = {}
    for i in rows:
        for f in sorted((store / "rows" / str(i)).rglob("*")):
            if f.is_file():
                st = f.stat()
                prints[f.relative_to(store).as_posix()] = (
                    st.st_ino, st.st_mtime_ns, hashlib.sha256(f.read_bytes()).hexdigest())
    assert prints
    return prints


def _store_prints(store: Path) -> dict:
    return {f.relative_to(store).as_posix(): (f.stat().st_ino, f.stat().st_mtime_ns,
                                              hashlib.sha256(f.read_bytes()).hexdigest())
            for f in sorted(store.rglob("*")) if f.is_file()}


def _leftovers(folder: Path) -> list[str]:
    """Hidden temporary siblings (``.T.zarr.PID.HEX.partial``...) and half-written rows."""
    found = [p.name for p in folder.iterdir() if p.name.startswith(".")]
    found += [p.name for p in folder.glob("*.zarr/rows/.*")]
    return found


def _interrupt_after(monkeypatch, calls: int) -> list[int]:
    """Make BlockCSRWriter.write_tile_row raise KeyboardInterrupt (Ctrl-C) once ``calls``
    tile rows are written; returns the list of rows written."""
    real = BlockCSRWriter.write_tile_row
    written: list[int] = []

    def write(self, i, block):
        if len(written) == calls:
            raise KeyboardInterrupt
        result = real(self, i, block)
        written.append(i)
        return result

    monkeypatch.setattr(BlockCSRWriter, "write_tile_row", write)
    return written


def _count_writes(monkeypatch) -> list[int]:
    real = BlockCSRWriter.write_tile_row
    written: list[int] = []

    def write(self, i, block):
        written.append(i)
        return real(self, i, block)

    monkeypatch.setattr(BlockCSRWriter, "write_tile_row", write)
    return written


def _build_argv(work, method="brute-force", captures=None, output="T.zarr", *extra,
                passes=True):
    """``bigT acquire build`` in tiles of 32, by default one tile row per pass."""
    return ["acquire", "build", str(work / f"{method}-patterns"),
            str(work / f"{captures or method}-captures"), "-o", str(work / output),
            "--tile-size", str(TILE), *(["--memory-limit", "4KiB"] if passes else []),
            "--no-progress", "--no-figures", "-q", *extra]


# --- in process -------------------------------------------------------------------------

@pytest.mark.parametrize("method", SETS)
@pytest.mark.parametrize("done", [1, 4])
def test_an_interrupted_build_resumes_to_the_same_T(work, rig, monkeypatch, method, done):
    out = work / "T.zarr"
    written = _interrupt_after(monkeypatch, done)
    with pytest.raises(KeyboardInterrupt):
        build_transport(work / f"{method}-patterns", work / f"{method}-captures", out,
                        tile_size=TILE, memory_bytes=BUDGET, progress=False)
    monkeypatch.undo()
    assert sorted(completed_rows(out, ROWS)) == sorted(written) and len(written) == done
    assert not read_store_attrs(out).complete
    with pytest.raises(IncompleteStoreError):
        open_store(out)
    kept = _row_prints(out, written)

    resumed = _count_writes(monkeypatch)
    report = build_transport(work / f"{method}-patterns", work / f"{method}-captures", out,
                             tile_size=TILE, memory_bytes=BUDGET, progress=False)
    assert sorted(resumed) == sorted(set(range(ROWS)) - set(written))  # only the others
    assert report.passes == ROWS - done  # < the ROWS passes of a build from scratch
    assert _row_prints(out, written) == kept  # the finished rows were not rewritten
    assert np.array_equal(_dense(out), _dense(rig / f"{method}-whole.zarr"))
    assert report.nnz == open_store(rig / f"{method}-whole.zarr").nnz
    assert not _leftovers(work)


def test_a_complete_build_is_not_redone_by_a_resume(work, rig):
    """Resuming means an interrupted store: a complete one is refused without
    --overwrite, whatever built it."""
    out = work / "T.zarr"
    shutil.copytree(rig / "brute-force-whole.zarr", out)
    before = _store_prints(out)
    with pytest.raises(StoreError, match="already exists"):
        build_transport(work / "brute-force-patterns", work / "brute-force-captures", out,
                        tile_size=TILE, progress=False)
    assert _store_prints(out) == before


# --- the command line: Ctrl-C -----------------------------------------------------------

def test_ctrl_c_returns_130_and_keeps_the_finished_tile_rows(work, rig, monkeypatch, capsys):
    """Ctrl-C while tile row 3 is being written: rows 0-2 stay, row 3 leaves nothing
    (not even a half-written directory), and the rerun of the same command finishes."""
    real = bigT.storage.writer.fmt.write_array_files

    def write_array(folder, *args):
        if Path(folder).name.startswith(".3."):  # an array of rows/.3.<hex>.partial
            raise KeyboardInterrupt
        return real(folder, *args)

    monkeypatch.setattr(bigT.storage.writer.fmt, "write_array_files", write_array)
    assert main(_build_argv(work)) == 130
    monkeypatch.undo()
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["bigT acquire build: interrupted; finished work on disk is kept"]
    out = work / "T.zarr"
    assert sorted(completed_rows(out, ROWS)) == [0, 1, 2]
    assert sorted(p.name for p in (out / "rows").iterdir()) == ["0", "1", "2", "zarr.json"]
    assert not read_store_attrs(out).complete
    assert (out / "acquisition" / "correspondence.npy").is_file()
    kept = _row_prints(out, [0, 1, 2])

    resumed = _count_writes(monkeypatch)
    # the same command again; the store's tile size is kept even when none is given
    argv = _build_argv(work)
    del argv[argv.index("--tile-size"):argv.index("--tile-size") + 2]
    assert main(argv + ["--json"]) == 0
    assert sorted(resumed) == [3, 4, 5]
    assert _row_prints(out, [0, 1, 2]) == kept
    assert open_store(out).tile_size == TILE
    assert np.array_equal(_dense(out), _dense(rig / "brute-force-whole.zarr"))
    assert not _leftovers(work)


def test_ctrl_c_before_any_row_leaves_a_store_that_resumes(work, rig, monkeypatch, capsys):
    _interrupt_after(monkeypatch, 0)
    assert main(_build_argv(work, "stripes")) == 130
    monkeypatch.undo()
    assert "interrupted" in capsys.readouterr().err
    assert completed_rows(work / "T.zarr", ROWS) == {}
    assert main(_build_argv(work, "stripes")) == 0
    assert np.array_equal(_dense(work / "T.zarr"), _dense(rig / "stripes-whole.zarr"))


# --- another build's leftovers ----------------------------------------------------------

@pytest.mark.parametrize("change, differ", [
    ({"captures": "other"}, "capture_files, captures, floor, floor_min, pixel_noise"),
    ({"extra": ("--floor", "0.01")}, "floor, floor_min"),    # other settings
])
def test_an_interrupted_build_of_other_captures_is_refused_unless_overwrite(
        work, rig, monkeypatch, capsys, change, differ):
    _interrupt_after(monkeypatch, 2)
    assert main(_build_argv(work, passes=False)) == 130
    monkeypatch.undo()
    capsys.readouterr()
    out = work / "T.zarr"
    assert len(completed_rows(out, ROWS)) == 2
    before = _store_prints(out)

    argv = _build_argv(work, "brute-force", change.get("captures"), "T.zarr",
                       *change.get("extra", ()), passes=False)
    assert main(argv) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in captured.err, captured.err
    assert lines[0] == (f"bigT acquire build: error: {out}: holds an interrupted build of "
                        f"other captures or settings ({differ} differ); pass --overwrite to "
                        "start again")
    assert _store_prints(out) == before  # the interrupted build is kept for its resume

    resumed = _count_writes(monkeypatch)
    assert main(argv + ["--overwrite"]) == 0
    assert sorted(resumed) == list(range(ROWS))  # started again, nothing reused
    assert not _leftovers(work)
    if "captures" in change:
        assert np.array_equal(_dense(out), _dense(rig / "other-whole.zarr"))
    assert open_store(out).metadata["acquisition"]["captures"] == str(
        (work / f"{change.get('captures', 'brute-force')}-captures").resolve())


def test_an_interrupted_build_is_not_resumed_on_a_retaken_capture(work, rig, monkeypatch,
                                                                   capsys):
    """The same folder, one capture replaced: the settings are the same but the rows
    already written hold the old capture's light; resuming would mix the two."""
    _interrupt_after(monkeypatch, 2)
    assert main(_build_argv(work, passes=False)) == 130
    monkeypatch.undo()
    capsys.readouterr()
    out = work / "T.zarr"
    before = _store_prints(out)
    retaken = work / "brute-force-captures" / "sp_100.png"
    shutil.copyfile(work / "other-captures" / "sp_100.png", retaken)  # another noise draw
    argv = _build_argv(work, passes=False)
    assert main(argv) == 2
    line = capsys.readouterr().err.strip()
    assert line == (f"bigT acquire build: error: {out}: holds an interrupted build of other "
                    "captures or settings (capture_files differ); pass --overwrite to start "
                    "again")
    assert _store_prints(out) == before
    assert main(argv + ["--overwrite"]) == 0
    assert not _leftovers(work)


def test_an_interrupted_overwrite_keeps_the_old_T(work, rig, monkeypatch, capsys):
    """--overwrite replaces a complete T only with a complete one: Ctrl-C half way
    leaves the old store byte for byte, and nothing beside it."""
    out = work / "T.zarr"
    shutil.copytree(rig / "brute-force-whole.zarr", out)
    before = _store_prints(out)
    _interrupt_after(monkeypatch, 3)
    argv = _build_argv(work, "brute-force", "other", "T.zarr", "--overwrite", passes=False)
    assert main(argv) == 130
    monkeypatch.undo()
    capsys.readouterr()
    assert _store_prints(out) == before
    assert not _leftovers(work)
    assert main(argv) == 0
    assert np.array_equal(_dense(out), _dense(rig / "other-whole.zarr"))
    assert not _leftovers(work)


# --- a process killed outright ----------------------------------------------------------

def test_a_build_killed_with_sigkill_resumes_to_the_same_T(work, rig):
    """``python -m bigT.cli acquire build`` in a child process, SIGKILLed as soon as its
    first tile row is marked complete on disk (each of the six passes reads all 194
    captures, so the kill lands long before the last row)."""
    out = work / "T.zarr"
    argv = [sys.executable, "-m", "bigT.cli", *_build_argv(work)]
    proc = subprocess.Popen(argv, cwd=work, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 60
        while not completed_rows(out, ROWS):
            assert proc.poll() is None, ("the build ended before a tile row was seen",
                                         proc.returncode, proc.stderr.read())
            assert time.monotonic() < deadline, "no tile row written within 60 s"
            time.sleep(0.002)
        os.kill(proc.pid, signal.SIGKILL)
        assert proc.wait(timeout=30) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)
        proc.stderr.close()

    done = sorted(completed_rows(out, ROWS))
    assert not read_store_attrs(out).complete, "the build finished before it was killed"
    assert 1 <= len(done) < ROWS
    kept = _row_prints(out, done)

    report = build_transport(work / "brute-force-patterns", work / "brute-force-captures",
                             out, tile_size=TILE, memory_bytes=BUDGET, progress=False)
    assert report.passes == ROWS - len(done)
    assert _row_prints(out, done) == kept
    assert np.array_equal(_dense(out), _dense(rig / "brute-force-whole.zarr"))
    assert not _leftovers(work)  # a row the kill cut half way is cleaned up by the resume
