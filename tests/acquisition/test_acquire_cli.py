"""``bigT acquire`` through bigT.cli.main: the loop end to end, every bad input of the
issue as one line naming the file (exit 2) with nothing written lost, a build
interrupted half way resuming to the same T, and the warnings printed (bigT's own
only)."""

import shutil
import warnings

import numpy as np
import pytest

from bigT import scenes
from bigT.acquisition import build_transport
from bigT.cli import main
from bigT.images import write_image
from bigT.storage import BlockCSRWriter
from bigT.storage import open as open_store


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """A 12x16 corner scene, brute-force patterns for a 24x32 projector in 2x2
    super-pixels, and their captures by a 30x40 camera."""
    root = tmp_path_factory.mktemp("rig")
    scenes.make("corner", (12, 16), root / "scene.zarr", density="exact", preview=False,
                progress=False)
    assert main(["acquire", "patterns", "--method", "brute-force", "--projector", "24x32",
                 "--superpixel", "2", "-o", str(root / "patterns"), "-q"]) == 0
    assert main(["acquire", "simulate", str(root / "scene.zarr"), str(root / "patterns"),
                 "-o", str(root / "captures"), "--camera", "30x40", "--noise", "0.001",
                 "--black", "0.02", "-q"]) == 0
    return root


@pytest.fixture
def work(rig, tmp_path):
    shutil.copytree(rig / "patterns", tmp_path / "patterns")
    shutil.copytree(rig / "captures", tmp_path / "captures")
    return tmp_path


def _build(work, *extra):
    return main(["acquire", "build", str(work / "patterns"), str(work / "captures"), "-o",
                 str(work / "T.zarr"), "--no-progress", *extra])


def _one_line_error(capsys, *words):
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    for w in words:
        assert w in lines[0], lines[0]
    return lines[0]


def test_the_loop_end_to_end_prints_what_it_did(work, capsys):
    assert _build(work) == 0
    out = capsys.readouterr().out
    assert "192 of 192 super-pixels seen" in out and "relative error" in out
    assert (work / "T-correspondence.png").stat().st_size > 1000
    assert (work / "T-validation.png").stat().st_size > 1000
    assert open_store(work / "T.zarr").shape == (192, 192)


def test_a_missing_capture(work, capsys):
    (work / "captures" / "sp_100.png").unlink()
    assert _build(work) == 2
    _one_line_error(capsys, "captures", "missing", "sp_100.png")
    assert not (work / "T.zarr").exists()


def test_an_extra_capture(work, capsys):
    shutil.copy(work / "captures" / "white.png", work / "captures" / "spare.png")
    assert _build(work) == 2
    _one_line_error(capsys, "captures", "spare.png", "match no pattern")


def test_a_capture_of_the_wrong_size(work, capsys):
    write_image(work / "captures" / "sp_007.png", np.zeros((30, 41)))
    assert _build(work) == 2
    _one_line_error(capsys, "sp_007.png", "30x41", "30x40")


def test_a_capture_of_another_bit_depth(work, capsys):
    write_image(work / "captures" / "sp_007.png", np.zeros((30, 40)), bits=8)
    assert _build(work) == 2
    _one_line_error(capsys, "sp_007.png", "uint8", "uint16")


def test_captures_that_are_all_black(work, capsys):
    for f in (work / "captures").glob("*.png"):
        write_image(f, np.full((30, 40), 0.02))
    assert _build(work) == 2
    _one_line_error(capsys, "white.png", "all black")


def test_a_manifest_of_another_projector(work, rig, capsys):
    assert main(["acquire", "patterns", "--method", "brute-force", "--projector", "12x16",
                 "--superpixel", "2", "-o", str(work / "small"), "-q"]) == 0
    assert main(["acquire", "simulate", str(rig / "scene.zarr"), str(work / "small"), "-o",
                 str(work / "cap2"), "--camera", "30x40"]) == 2
    _one_line_error(capsys, "small", "6x8 super-pixel grid", "12x16")
    # and those patterns' manifest against the other captures
    assert main(["acquire", "build", str(work / "small"), str(work / "captures"), "-o",
                 str(work / "T.zarr")]) == 2
    _one_line_error(capsys, "captures", "missing")


def test_a_damaged_manifest(work, capsys):
    (work / "patterns" / "manifest.json").write_text("{not json")
    assert _build(work) == 2
    _one_line_error(capsys, "manifest.json", "not JSON")


def test_graycode_alone_cannot_make_T(work, capsys):
    assert main(["acquire", "patterns", "--method", "graycode", "--projector", "24x32",
                 "--superpixel", "2", "-o", str(work / "gc"), "-q"]) == 0
    assert main(["acquire", "build", str(work / "gc"), str(work / "captures"), "-o",
                 str(work / "T.zarr")]) == 2
    _one_line_error(capsys, "gc", "correspondence, not T")


def test_an_unreadable_capture(work, capsys):
    (work / "captures" / "sp_003.png").write_bytes(b"not a png at all")
    assert _build(work) == 2
    _one_line_error(capsys, "sp_003.png", "cannot read")


@pytest.mark.parametrize("argv, words", [
    (["patterns", "--method", "stripes", "--projector", "24x32", "--superpixel", "5"],
     ["do not divide", "5x5"]),
    (["patterns", "--method", "stripes", "--projector", "0x32"], ["--projector"]),
    (["build", "P", "C", "-o", "T.zarr", "--gamma", "0"], ["--gamma"]),
    (["simulate", "S", "P", "-o", "C", "--camera", "0x5"], ["--camera"]),
])
def test_bad_options(tmp_path, capsys, argv, words):
    if argv[0] == "patterns":
        argv = argv + ["-o", str(tmp_path / "p")]
    assert main(["acquire", *argv]) == 2
    _one_line_error(capsys, *words)


def test_an_existing_store_is_kept_unless_overwrite(work, capsys):
    assert _build(work) == 0
    before = open_store(work / "T.zarr").to_scipy().toarray()
    (work / "captures" / "sp_100.png").unlink()
    assert _build(work, "--overwrite") == 2  # refused before anything is replaced
    capsys.readouterr()
    assert np.array_equal(open_store(work / "T.zarr").to_scipy().toarray(), before)
    shutil.copy(work / "captures" / "sp_101.png", work / "captures" / "sp_100.png")
    assert _build(work) == 2
    _one_line_error(capsys, "T.zarr", "already exists")


def test_an_interrupted_build_resumes_to_the_same_T(work, monkeypatch, capsys):
    assert main(["acquire", "build", str(work / "patterns"), str(work / "captures"), "-o",
                 str(work / "whole.zarr"), "--tile-size", "32", "-q"]) == 0
    real = BlockCSRWriter.write_tile_row
    calls = []

    def interrupted(self, i, block):
        if len(calls) == 3:
            raise KeyboardInterrupt
        calls.append(i)
        return real(self, i, block)

    monkeypatch.setattr(BlockCSRWriter, "write_tile_row", interrupted)
    assert _build(work, "--tile-size", "32") == 130
    assert "interrupted" in capsys.readouterr().err
    from bigT.storage import completed_rows

    assert sorted(completed_rows(work / "T.zarr", 6)) == sorted(calls)  # 3 of 6 kept
    resumed = []

    def counted(self, i, block):
        resumed.append(i)
        return real(self, i, block)

    monkeypatch.setattr(BlockCSRWriter, "write_tile_row", counted)
    report = build_transport(work / "patterns", work / "captures", work / "T.zarr",
                             tile_size=32, progress=False)
    assert report.passes == 1 and sorted(resumed + calls) == list(range(6))
    a = open_store(work / "T.zarr").to_scipy().toarray()
    assert np.array_equal(a, open_store(work / "whole.zarr").to_scipy().toarray())


def test_an_interrupted_build_of_other_captures_is_not_resumed(work, monkeypatch, capsys):
    def interrupted(self, i, block):
        raise KeyboardInterrupt

    monkeypatch.setattr(BlockCSRWriter, "write_tile_row", interrupted)
    assert _build(work, "--tile-size", "32") == 130
    monkeypatch.undo()
    capsys.readouterr()
    assert _build(work, "--tile-size", "32", "--floor", "0.01") == 2
    _one_line_error(capsys, "T.zarr", "interrupted build of other captures or settings")
    assert _build(work, "--tile-size", "32", "--floor", "0.01", "--overwrite") == 0


def test_the_summary_names_the_black_level_and_where_it_came_from(work, capsys):
    black = work / "black.npy"
    np.save(black, np.full((30, 40), 0.02, np.float32))
    assert _build(work, "--black", str(black), "--no-figures") == 0
    out = capsys.readouterr().out
    assert "black level 0.02 (from --black black.npy)" in out
    assert _build(work, "-o", str(work / "T2.zarr"), "--no-figures") == 0
    assert "(from the black capture)" in capsys.readouterr().out


def test_only_bigTs_own_warnings_are_printed_as_the_commands(work, monkeypatch, capsys):
    """A library's warning during the build is not bigT's to print under its name: it
    goes to Python's warning machinery as usual. bigT's (a tile row over the memory
    limit) is printed once, as ``bigT acquire build: warning: ...``."""
    import bigT.acquisition

    real = bigT.acquisition.build_transport

    def build(*args, **kwargs):
        warnings.warn("some library's deprecation", DeprecationWarning)
        return real(*args, **kwargs)

    monkeypatch.setattr(bigT.acquisition, "build_transport", build)
    with pytest.warns(DeprecationWarning, match="some library's"):
        assert _build(work, "--tile-size", "32", "--memory-limit", "1KiB", "--no-figures",
                      "-q") == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("bigT acquire build: warning: tile row 0 of T alone holds more "
                             "entries than the memory limit of 1024 bytes")
