"""Every bad input of ``bigT acquire`` through ``bigT.cli.main``: exit status 2, one line
on stderr, ``bigT acquire STEP: error: FILE: what``, naming the offending file or
folder and saying what is wrong, no traceback, and nothing already on disk changed --
an existing complete T.zarr stays byte for byte as it was, even under ``--overwrite``.

The rig (a 12x16 corner scene, pattern sets for a 24x32 projector in 2x2 super-pixels,
their captures by a 30x40 camera, a complete T) is built once per module; each test
damages its own copy.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from bigT import scenes
from bigT.acquisition import Manifest, read_manifest
from bigT.cli import main
from bigT.errors import AcquisitionError
from bigT.images import read_raw_image, write_image
from bigT.storage import open as open_store

CAMERA = (30, 40)
PROJECTOR = "24x32"  # 2x2 super-pixels: the scene's 12x16 grid
SETS = {  # name -> (method, --graycode)
    "bf": ("brute-force", False),
    "gc": ("brute-force", True),  # correspondence by Gray code: T's captures read last
    "stripes": ("stripes", False),
    "graycode": ("graycode", False),
}


# --- the rig --------------------------------------------------------------------------

@pytest.fixture(scope="module")
def rig(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("rig")
    scenes.make("corner", (12, 16), root / "scene.zarr", density="exact", preview=False,
                progress=False)
    for name, (method, graycode) in SETS.items():
        assert main(["acquire", "patterns", "--method", method, "--projector", PROJECTOR,
                     "--superpixel", "2", "-o", str(root / f"{name}-patterns"), "-q"]
                    + (["--graycode"] if graycode else [])) == 0
        assert main(["acquire", "simulate", str(root / "scene.zarr"),
                     str(root / f"{name}-patterns"), "-o", str(root / f"{name}-captures"),
                     "--camera", "30x40", "--noise", "0.001", "--black", "0.02", "-q"]) == 0
    # a complete T every test keeps beside its inputs: no failure may touch it
    assert main(["acquire", "build", str(root / "bf-patterns"), str(root / "bf-captures"),
                 "-o", str(root / "T.zarr"), "--tile-size", "96", "--no-figures", "-q"]) == 0
    return root


@pytest.fixture
def work(rig, tmp_path) -> Path:
    """A copy of the rig's brute-force patterns and captures and of its complete T.zarr
    (other sets: :func:`_copy`)."""
    _copy(rig, tmp_path, "bf")
    shutil.copytree(rig / "T.zarr", tmp_path / "T.zarr")
    return tmp_path


def _copy(rig: Path, work: Path, *names: str) -> None:
    """Copy the pattern and capture folders of the sets ``names`` into ``work``."""
    for name in names:
        for kind in ("patterns", "captures"):
            if not (work / f"{name}-{kind}").exists():
                shutil.copytree(rig / f"{name}-{kind}", work / f"{name}-{kind}")


# --- helpers --------------------------------------------------------------------------

def _fingerprint(root: Path) -> dict[str, tuple]:
    """Every file and folder under ``root``: inode, size and modification time (a
    replacement changes the inode, a rewrite the time), and for the files of stores
    (``*.zarr``) a hash of their bytes too."""
    prints = {}
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root).as_posix()
        if any(part.startswith(".bigT-") for part in Path(rel).parts):
            continue  # locks and reader leases: bookkeeping, not data
        st = path.stat()
        if path.is_dir():
            prints[rel] = (st.st_ino, "dir")
        else:
            digest = (hashlib.sha256(path.read_bytes()).hexdigest()
                      if ".zarr/" in rel else None)
            prints[rel] = (st.st_ino, st.st_size, st.st_mtime_ns, digest)
    return prints


def _fails(argv, capsys, *, step: str, names, says, world: Path) -> str:
    """Run ``bigT acquire STEP ...`` and check the failure: status 2, one line on stderr
    naming ``names`` (a path, or a list of them) and saying each of ``says``, and nothing
    under ``world`` changed, created or removed. Returns the line."""
    before = _fingerprint(world)
    status = main(["acquire", step, *map(str, argv)])
    out, err = capsys.readouterr()
    assert "Traceback" not in out + err, err
    assert status == 2, (status, out, err)
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    line = lines[0]
    assert line.startswith(f"bigT acquire {step}: error: "), line
    for path in names if isinstance(names, list) else [names]:
        assert str(path) in line, (str(path), line)
    for words in [says] if isinstance(says, str) else says:
        assert words in line, (words, line)
    assert _fingerprint(world) == before, "a failed command changed what was on disk"
    return line


def _build(work, name="bf", *extra, output="T.zarr"):
    """The argv of ``bigT acquire build`` on set ``name`` of ``work``, onto the complete
    T.zarr with --overwrite (the strongest case: the old T must survive a failure)."""
    return [work / f"{name}-patterns", work / f"{name}-captures", "-o", work / output,
            "--overwrite", "--no-progress", *extra]


def _capture_like(path: Path, shape=CAMERA, bits=16, value=0.3) -> None:
    path.unlink()
    write_image(path, np.full(shape, value), bits=bits)


# --- 1. a missing capture ---------------------------------------------------------------

@pytest.mark.parametrize("name, missing", [("bf", "sp_100.png"), ("bf", "black.png"),
                                           ("gc", "gray_col_02_inv.png"),
                                           ("stripes", "col_07.png")])
def test_a_missing_capture(work, rig, capsys, name, missing):
    _copy(rig, work, name)
    (work / f"{name}-captures" / missing).unlink()
    line = _fails(_build(work, name), capsys, step="build", names=work / f"{name}-captures",
                  says=["1 of", "captures missing", missing], world=work)
    assert "each pattern needs a capture of the same name" in line


def test_a_missing_capture_without_overwrite_and_no_old_store(work, capsys):
    (work / "T.zarr").rename(work / "kept.zarr")
    (work / "bf-captures" / "sp_000.png").unlink()
    argv = _build(work)
    argv.remove("--overwrite")
    _fails(argv, capsys, step="build", names=work / "bf-captures", says="sp_000.png",
           world=work)
    assert not (work / "T.zarr").exists()  # nothing started


# --- 2. an extra capture ----------------------------------------------------------------

@pytest.mark.parametrize("extra", ["sp_999.png", "IMG_0001.tif"])
def test_an_extra_capture(work, capsys, extra):
    write_image(work / "bf-captures" / extra, np.full(CAMERA, 0.3))
    _fails(_build(work), capsys, step="build", names=work / "bf-captures",
           says=[extra, "match no pattern", "another pattern set"], world=work)


def test_two_captures_of_one_pattern(work, capsys):
    write_image(work / "bf-captures" / "sp_042.npy", np.full(CAMERA, 0.3))
    _fails(_build(work), capsys, step="build", names=work / "bf-captures",
           says=["two captures of pattern sp_042", "sp_042.npy", "sp_042.png"], world=work)


def test_files_that_are_not_images_are_no_extra_captures(work, capsys):
    """simulation.json, notes and hidden files beside the captures are ignored."""
    (work / "bf-captures" / "README.txt").write_text("rig notes")
    (work / "T.zarr").rename(work / "old.zarr")
    assert main(["acquire", "build", *map(str, _build(work)), "--no-figures", "-q"]) == 0
    capsys.readouterr()


# --- 3. a capture of the wrong size -----------------------------------------------------

@pytest.mark.parametrize("name, odd", [
    ("bf", "sp_007.png"),     # read while finding the correspondence
    ("bf", "white.png"),      # read first of all after the black
    ("bf", "black.png"),      # the first capture read: the others are the reference
    ("gc", "sp_007.png"),     # Gray code: T's captures are read only while writing T
    ("stripes", "row_03.png"),
])
def test_a_capture_of_the_wrong_size(work, rig, capsys, name, odd):
    _copy(rig, work, name)
    _capture_like(work / f"{name}-captures" / odd, shape=(30, 41))
    _fails(_build(work, name), capsys, step="build", names=work / f"{name}-captures" / odd,
           says=["capture of 30x41 pixels", "the others are 30x40"], world=work)


def test_a_black_frame_of_the_wrong_size(work, capsys):
    write_image(work / "black-frame.npy", np.zeros((40, 30)))
    _fails(_build(work, "bf", "--black", work / "black-frame.npy"), capsys, step="build",
           names=work / "black-frame.npy", says=["40x30", "30x40"], world=work)


def test_a_black_frame_in_raw_counts(work, capsys):
    """The mean of 16-bit black frames taken in numpy keeps their counts (1300, not
    0.02): it was subtracted as it was, and the white capture blamed for being black."""
    counts = read_raw_image(work / "bf-captures" / "black.png").astype(np.float32)
    np.save(work / "black-counts.npy", counts)
    _fails(_build(work, "bf", "--black", work / "black-counts.npy"), capsys, step="build",
           names=work / "black-counts.npy",
           says=["black level up to", "not raw counts", "divide it by 65535"], world=work)


def test_the_captures_folder_cannot_be_the_pattern_folder(work, capsys):
    """The patterns have the captures' names: they would be read as captures."""
    for patterns in (work / "bf-patterns", work / "bf-patterns" / "manifest.json"):
        _fails([patterns, work / "bf-patterns", "-o", work / "T.zarr", "--overwrite"], capsys,
               step="build", names=work / "bf-patterns",
               says="the captures folder is the pattern folder", world=work)


def test_simulating_into_the_pattern_folder_is_refused(work, rig, capsys):
    _fails([rig / "scene.zarr", work / "bf-patterns", "-o", work / "bf-patterns", "--camera",
            "30x40"], capsys, step="simulate", names=work / "bf-patterns",
           says=["the captures folder is the pattern folder", "would overwrite them"],
           world=work)


def test_a_missing_black_frame(work, capsys):
    _fails(_build(work, "bf", "--black", work / "nope.png"), capsys, step="build",
           names=work / "nope.png", says="no such file", world=work)


# --- 4. a capture of another bit depth --------------------------------------------------

@pytest.mark.parametrize("name, odd", [("bf", "sp_123.png"), ("bf", "white.png"),
                                       ("bf", "black.png"), ("gc", "sp_123.png"),
                                       ("stripes", "col_00.png")])
def test_a_capture_of_another_bit_depth(work, rig, capsys, name, odd):
    _copy(rig, work, name)
    _capture_like(work / f"{name}-captures" / odd, bits=8)
    assert read_raw_image(work / f"{name}-captures" / odd).dtype == np.uint8
    _fails(_build(work, name), capsys, step="build", names=work / f"{name}-captures" / odd,
           says=["pixel type uint8", "uint16", "mixed bit depths"], world=work)


@pytest.mark.parametrize("odd", ["sp_123.png", "white.png", "black.png"])
def test_a_colour_capture_is_called_colour_not_another_bit_depth(work, capsys, odd):
    """An 8-bit RGB PNG among 16-bit grayscale captures: its pixel type differs too,
    but what to fix is the colour."""
    import imageio.v3 as iio

    path = work / "bf-captures" / odd
    path.unlink()
    iio.imwrite(path, np.full(CAMERA + (3,), 80, np.uint8))
    line = _fails(_build(work), capsys, step="build", names=path,
                  says=["a colour capture (3 channels)", "grayscale"], world=work)
    assert "bit depth" not in line


def test_a_float_capture_among_16_bit_ones(work, capsys):
    (work / "bf-captures" / "sp_050.png").unlink()
    write_image(work / "bf-captures" / "sp_050.npy", np.full(CAMERA, 0.3))
    _fails(_build(work), capsys, step="build", names=work / "bf-captures" / "sp_050.npy",
           says=["pixel type float32", "uint16"], world=work)


# --- 5. a manifest of another projector size --------------------------------------------

@pytest.mark.parametrize("projector, superpixel, grid", [("12x16", "2", "6x8"),
                                                         ("16x12", "1", "16x12")])
def test_simulating_patterns_of_another_grid_than_the_scene(work, rig, capsys, projector,
                                                            superpixel, grid):
    other = work / "other-patterns"
    assert main(["acquire", "patterns", "--method", "brute-force", "--projector", projector,
                 "--superpixel", superpixel, "-o", str(other), "-q"]) == 0
    _fails([rig / "scene.zarr", other, "-o", work / "new-captures", "--camera", "30x40",
            "--no-progress"], capsys, step="simulate", names=other,
           says=[f"patterns are for a {grid} super-pixel grid", "the scene is 12x16"],
           world=work)
    assert not (work / "new-captures").exists()


def test_simulating_into_existing_captures_of_another_grid_keeps_them(work, rig, capsys):
    other = work / "other-patterns"
    assert main(["acquire", "patterns", "--method", "stripes", "--projector", "12x16",
                 "--superpixel", "2", "-o", str(other), "-q"]) == 0
    _fails([rig / "scene.zarr", other, "-o", work / "bf-captures", "--camera", "30x40"],
           capsys, step="simulate", names=other, says="6x8 super-pixel grid", world=work)


@pytest.mark.parametrize("patterns, captures, says", [
    ("stripes", "bf", ["captures missing", "row_00.png"]),   # captures of another method
    ("bf", "stripes", ["captures missing", "sp_000.png"]),
    ("bf", "gc", ["match no pattern", "gray_col_00.png"]),    # a set with Gray code
    ("small", "bf", ["captures missing", "sp_00.png"]),       # another projector size
])
def test_building_captures_against_the_manifest_of_another_set(work, rig, capsys, patterns,
                                                                captures, says):
    _copy(rig, work, "stripes", "gc")
    assert main(["acquire", "patterns", "--method", "brute-force", "--projector", "12x16",
                 "--superpixel", "2", "-o", str(work / "small-patterns"), "-q"]) == 0
    argv = [work / f"{patterns}-patterns", work / f"{captures}-captures", "-o",
            work / "T.zarr", "--overwrite"]
    _fails(argv, capsys, step="build", names=work / f"{captures}-captures", says=says,
           world=work)


# --- 6. captures that are all black -----------------------------------------------------

@pytest.mark.parametrize("name, level", [("bf", 0.0), ("bf", 0.02), ("gc", 0.0),
                                         ("stripes", 0.02)])
def test_captures_that_are_all_black(work, rig, capsys, name, level):
    _copy(rig, work, name)
    folder = work / f"{name}-captures"
    for f in folder.glob("*.png"):
        _capture_like(f, value=level)
    _fails(_build(work, name), capsys, step="build", names=folder / "white.png",
           says=["all black", "no brighter than the black one"], world=work)


def test_all_black_8_bit_captures(work, rig, capsys):
    folder = work / "bf8-captures"
    assert main(["acquire", "simulate", str(rig / "scene.zarr"), str(work / "bf-patterns"),
                 "-o", str(folder), "--camera", "30x40", "--format", "png8", "-q"]) == 0
    for f in folder.glob("*.png"):
        _capture_like(f, bits=8, value=0.0)
    shutil.copytree(work / "bf-patterns", work / "bf8-patterns")
    _fails(_build(work, "bf8"), capsys, step="build", names=folder / "white.png",
           says="all black", world=work)


# --- 7. a corrupted or edited manifest --------------------------------------------------

@pytest.mark.parametrize("content, says", [
    (b"{not json", "not JSON"),
    (b"", "not JSON"),
    (b"\xff\xfe\x00\x89PNG garbage \x00\x01", "not JSON"),     # not even text
    (b"[1, 2, 3]", "not a valid bigT pattern manifest"),
    (b'{"format": "something else"}', "not a valid bigT pattern manifest"),
])
def test_a_corrupted_manifest(work, capsys, content, says):
    manifest = work / "bf-patterns" / "manifest.json"
    manifest.write_bytes(content)
    _fails(_build(work), capsys, step="build", names=manifest, says=says, world=work)


def test_a_truncated_manifest(work, capsys):
    manifest = work / "bf-patterns" / "manifest.json"
    manifest.write_bytes(manifest.read_bytes()[:300])
    _fails(_build(work), capsys, step="build", names=manifest, says="not JSON", world=work)


def test_a_missing_manifest(work, capsys):
    (work / "bf-patterns" / "manifest.json").unlink()
    _fails(_build(work), capsys, step="build", names=work / "bf-patterns" / "manifest.json",
           says="no pattern manifest", world=work)


def _edited(path: Path, **changes) -> dict:
    d = json.loads(path.read_text())
    d.update(changes)
    path.write_text(json.dumps(d))
    return d


@pytest.mark.parametrize("changes, says", [
    ({"projector": [12, 16]}, "pattern list is not the one bigT writes"),   # 6x8 grid
    ({"projector": [24, 30]}, "pattern list is not the one bigT writes"),
    ({"projector": [25, 32]}, "do not divide into 2x2 super-pixels"),       # s no divisor
    ({"projector": [24, 32, 3]}, "projector has a wrong value"),
    ({"projector": [0, 32]}, "projector must be a positive integer"),
    ({"projector": "24x32"}, "projector must be a positive integer"),
    ({"superpixel": 5}, "do not divide into 5x5 super-pixels"),
    ({"superpixel": 4}, "pattern list is not the one bigT writes"),
    ({"method": "stripes"}, "pattern list is not the one bigT writes"),
    ({"method": "laser"}, "wrong value"),
    ({"version": 2}, "version 2"),
])
def test_a_manifest_edited_to_another_projector(work, capsys, changes, says):
    manifest = work / "bf-patterns" / "manifest.json"
    d = _edited(manifest, **changes)
    with pytest.raises(AcquisitionError) as info:
        Manifest.from_dict(d, manifest)
    assert info.value.path == str(manifest) and says in str(info.value)
    _fails(_build(work), capsys, step="build", names=manifest,
           says=["not a valid bigT pattern manifest", says], world=work)


def test_an_edited_manifest_is_refused_by_simulate_too(work, rig, capsys):
    manifest = work / "bf-patterns" / "manifest.json"
    _edited(manifest, projector=[12, 16])
    _fails([rig / "scene.zarr", work / "bf-patterns", "-o", work / "new", "--camera", "30x40"],
           capsys, step="simulate", names=manifest, says="not a valid bigT pattern manifest",
           world=work)
    assert not (work / "new").exists()


def test_a_float_index_in_the_manifest_builds_as_its_integer(work, rig, capsys):
    """5.0 equals 5, so the manifest passes; the canonical manifest is what is used (a
    float reached numpy as an index: a traceback)."""
    manifest = work / "bf-patterns" / "manifest.json"
    d = json.loads(manifest.read_text())
    for entry in d["patterns"]:
        if "index" in entry:
            entry["index"] = float(entry["index"])
    manifest.write_text(json.dumps(d))
    assert read_manifest(work / "bf-patterns").of_kind("superpixel")[7].index == 7
    argv = _build(work, "bf", "--no-figures", "-q", output="new.zarr")
    argv.remove("--overwrite")
    assert main(["acquire", "build", *map(str, argv)]) == 0, capsys.readouterr().err
    assert np.array_equal(open_store(work / "new.zarr").to_scipy().toarray(),
                          open_store(rig / "T.zarr").to_scipy().toarray())


@pytest.mark.parametrize("step", ["build", "patterns"])
def test_a_huge_projector_is_refused_at_once(work, capsys, step):
    """A manifest edited to a 100000x100000 projector (10^10 brute-force patterns), or
    asked for: refused in one line before any pattern is listed. Run in a child process
    with a time and memory limit, so that a regression fails rather than hangs."""
    import resource
    import subprocess
    import sys

    manifest = work / "bf-patterns" / "manifest.json"
    _edited(manifest, projector=[100000, 100000], superpixel=1)
    before = _fingerprint(work)
    if step == "build":
        argv = [*map(str, _build(work))]
    else:
        argv = ["--method", "brute-force", "--projector", "100000x100000", "-o",
                str(work / "huge")]

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (8 << 30, 8 << 30))

    proc = subprocess.run([sys.executable, "-m", "bigT.cli", "acquire", step, *argv],
                          capture_output=True, text=True, timeout=120, preexec_fn=limit)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr[-2000:]
    # 10^10 super-pixels, black and white, and the default ramp of 17 levels
    assert "needs 10000000019 patterns" in lines[0] and "--superpixel" in lines[0]
    if step == "build":
        assert lines[0].startswith(f"bigT acquire build: error: {manifest}: not a valid")
    assert _fingerprint(work) == before


def test_an_edited_pattern_entry(work, capsys):
    manifest = work / "bf-patterns" / "manifest.json"
    d = json.loads(manifest.read_text())
    d["patterns"][5]["index"] = 7  # two patterns lighting super-pixel 7
    manifest.write_text(json.dumps(d))
    _fails(_build(work), capsys, step="build", names=manifest,
           says="pattern list is not the one bigT writes", world=work)


def test_the_written_manifest_reads_back(work):
    m = read_manifest(work / "bf-patterns")
    # 194 patterns of brute force and Gray code, and the default ramp of 17 levels
    assert m.projector == (24, 32) and m.grid == (12, 16) and len(m.patterns) == 194 + 17


# --- 8. Gray code alone -----------------------------------------------------------------

@pytest.mark.parametrize("captures", ["graycode", "bf"])
def test_graycode_patterns_alone_cannot_make_T(work, rig, capsys, captures):
    _copy(rig, work, "graycode")
    _fails([work / "graycode-patterns", work / f"{captures}-captures", "-o", work / "T.zarr",
            "--overwrite"], capsys, step="build", names=work / "graycode-patterns",
           says=["Gray-code patterns give the correspondence, not T", "--method brute-force"],
           world=work)


# --- 9. bad option values ---------------------------------------------------------------

@pytest.mark.parametrize("argv, says", [
    (["patterns", "--method", "stripes", "--projector", "24x32", "--superpixel", "5"],
     ["24x32", "do not divide into 5x5"]),
    (["patterns", "--method", "brute-force", "--projector", "24x32", "--superpixel", "64"],
     "do not divide into 64x64"),
    (["patterns", "--method", "brute-force", "--projector", "24x32", "--superpixel", "0"],
     ["--superpixel", ">= 1"]),
    (["patterns", "--method", "brute-force", "--projector", "0x32"], "--projector"),
    (["patterns", "--method", "brute-force", "--projector", "24by32"], "HxW"),
    (["patterns", "--method", "laser", "--projector", "24x32"], "--method"),
    (["build", "P", "C", "-o", "T.zarr", "--gamma", "0"], ["--gamma", "> 0"]),
    (["build", "P", "C", "-o", "T.zarr", "--gamma", "-2"], "--gamma"),
    (["build", "P", "C", "-o", "T.zarr", "--floor", "-1"], "--floor"),
    (["build", "P", "C", "-o", "T.zarr", "--memory-limit", "0"], "--memory-limit"),
    (["build", "P", "C", "-o", "T.zarr", "--memory-limit", "lots"], "--memory-limit"),
    (["build", "P", "C", "-o", "T.zarr", "--tile-size", "0"], "--tile-size"),
    (["simulate", "S", "P", "-o", "C", "--camera", "0x5"], ["--camera", "0x5"]),
    (["simulate", "S", "P", "-o", "C", "--camera", "30"], "--camera"),
    (["simulate", "S", "P", "-o", "C", "--camera", "30x40", "--gamma", "0"], "--gamma"),
    (["simulate", "S", "P", "-o", "C", "--camera", "30x40", "--noise", "-0.1"], "--noise"),
    (["simulate", "S", "P", "-o", "C", "--camera", "30x40", "--black", "2"], "--black"),
    (["simulate", "S", "P", "-o", "C", "--camera", "30x40", "--format", "jpg"], "--format"),
])
def test_bad_option_values(tmp_path, capsys, argv, says):
    step, rest = argv[0], [str(tmp_path / a) if a in ("P", "C", "S", "T.zarr") else a
                           for a in argv[1:]]
    if step == "patterns":
        rest += ["-o", str(tmp_path / "out")]
    before = sorted(tmp_path.iterdir())
    status = main(["acquire", step, *rest])
    err = capsys.readouterr().err
    assert status == 2 and "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"bigT acquire {step}: error: "), lines[0]
    for words in [says] if isinstance(says, str) else says:
        assert words in lines[0], (words, lines[0])
    assert sorted(tmp_path.iterdir()) == before  # nothing written


# --- 10. an unreadable capture ----------------------------------------------------------

@pytest.mark.parametrize("name, odd, damage", [
    ("bf", "sp_003.png", "garbage"), ("bf", "sp_003.png", "truncated"),
    ("bf", "black.png", "garbage"), ("bf", "white.png", "truncated"),
    ("gc", "sp_003.png", "garbage"),          # Gray code: read only while writing T
    ("gc", "gray_row_01.png", "truncated"), ("stripes", "row_11.png", "garbage")])
def test_an_unreadable_capture(work, rig, capsys, name, odd, damage):
    _copy(rig, work, name)
    path = work / f"{name}-captures" / odd
    raw = path.read_bytes()
    path.write_bytes(b"not a png at all" * 8 if damage == "garbage" else raw[:len(raw) // 2])
    _fails(_build(work, name), capsys, step="build", names=path, says="cannot read the image",
           world=work)


def test_a_folder_named_like_a_capture(work, capsys):
    """A folder with an image's name is not a capture: the pattern's capture is missing."""
    path = work / "bf-captures" / "sp_010.png"
    path.unlink()
    path.mkdir()
    _fails(_build(work), capsys, step="build", names=work / "bf-captures",
           says=["missing", "sp_010.png"], world=work)


def test_no_captures_folder(work, capsys):
    _fails([work / "bf-patterns", work / "nowhere", "-o", work / "T.zarr", "--overwrite"],
           capsys, step="build", names=work / "nowhere", says="no such captures folder",
           world=work)


# --- what survives ----------------------------------------------------------------------

def test_the_old_T_is_kept_by_a_failed_overwrite_and_replaced_by_a_good_one(work, rig,
                                                                              capsys):
    _copy(rig, work, "gc")
    """The acquisition's own --overwrite: the old store goes only when the new is whole."""
    old = _fingerprint(work / "T.zarr")
    _capture_like(work / "gc-captures" / "sp_150.png", bits=8)  # found while writing T
    _fails(_build(work, "gc"), capsys, step="build", names=work / "gc-captures" / "sp_150.png",
           says="mixed bit depths", world=work)
    assert _fingerprint(work / "T.zarr") == old
    assert not [p for p in work.iterdir() if p.name.startswith(".")]  # no leftovers
    shutil.rmtree(work / "gc-captures")
    shutil.copytree(work / "bf-captures", work / "gc-captures")
    shutil.rmtree(work / "gc-patterns")
    shutil.copytree(work / "bf-patterns", work / "gc-patterns")
    assert main(["acquire", "build", *map(str, _build(work, "gc")), "--no-figures", "-q"]) == 0
    assert _fingerprint(work / "T.zarr") != old
    assert not [p for p in work.iterdir() if p.name.startswith(".")]


def test_a_build_onto_a_complete_store_without_overwrite_is_refused(work, capsys):
    argv = _build(work)
    argv.remove("--overwrite")
    _fails(argv, capsys, step="build", names=work / "T.zarr",
           says=["already exists", "--overwrite"], world=work)


def test_a_build_onto_a_folder_of_the_users_is_refused_even_with_overwrite(work, capsys):
    (work / "mine").mkdir()
    (work / "mine" / "keep.txt").write_text("keep me")
    _fails(_build(work, output="mine"), capsys, step="build", names=work / "mine",
           says="not a bigT store", world=work)
