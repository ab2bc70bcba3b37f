"""Every bad input to every ``bigT`` subcommand: one line on stderr naming the problem
(and the file, when there is one), exit status 2, no traceback, and nothing already on
disk changed (issue #17, items 5-7).

Two walks. The option walk is generated from ``bigT.cli.build_parser()``: every option
that takes a value of a type or from a list gets nonsense values, so an option or
subcommand added later is covered without editing this file (and an option taking free
text must be listed in :data:`FREE_TEXT`). The file walk runs each subcommand on
damaged, mistyped or misplaced files and folders built once in a small world; the whole
world is fingerprinted before and after every case.
"""

from __future__ import annotations

import argparse
import errno
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import scipy.io
import scipy.sparse as sp

import bigT.storage.convert
from bigT import config
from bigT.cli import build_parser, main
from bigT.storage import from_scipy

H, W = 4, 5  # the world's images; its T is (H W) x (H W)
N = H * W

#: Values no typed option accepts (the limits of each option are checked by
#: test_bounded_values_name_their_bound): not a number, NaN, infinity, a negative number.
NONSENSE = ("abc", "nan", "inf", "-1")

#: Options that take free text (paths, names); every other option taking a value must
#: have a ``type`` or ``choices`` for the option walk to check.
FREE_TEXT = {"-o", "--output", "--var", "--json", "--first-bounce", "--simulate",
             "--matrix-free", "--dir", "--projector-response"}


# --- the parser ---------------------------------------------------------------------------

def _subcommands() -> dict[str, argparse.ArgumentParser]:
    group = next(a for a in build_parser()._actions
                 if isinstance(a, argparse._SubParsersAction))
    return dict(group.choices)


def _valued_options():
    """(subcommand, option, action) for every option of every subcommand that takes a
    value."""
    for name, parser in _subcommands().items():
        for action in parser._actions:
            if action.option_strings and action.nargs != 0 and action.dest != "help":
                yield name, action.option_strings[-1], action


def _option_cases():
    for name, option, action in _valued_options():
        if action.type is not None:
            for value in NONSENSE:
                if action.choices is None or value not in map(str, action.choices):
                    yield pytest.param(name, option, value, id=f"{name} {option}={value}")
        elif action.choices is not None:
            yield pytest.param(name, option, "bogus", id=f"{name} {option}=bogus")


# --- running a command ----------------------------------------------------------------

def _run(argv, capsys) -> tuple[int, list[str], str]:
    """``bigT argv`` in this process: (status, non-empty stderr lines, all output)."""
    status = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return status, [line for line in err.splitlines() if line.strip()], out + err


def _assert_one_line_error(argv, capsys, *, names=None, says=None) -> str:
    status, lines, text = _run(argv, capsys)
    assert "Traceback" not in text, text
    assert status == 2, (status, text)
    assert len(lines) == 1, lines
    command = f"bigT {argv[0]}" if str(argv[0]) in _subcommands() else "bigT"
    if str(argv[0]) == "acquire" and len(argv) > 1 and not str(argv[1]).startswith("-"):
        command += f" {argv[1]}"  # a command with steps names the step
    assert lines[0].startswith(f"{command}: error: "), lines[0]
    if names is not None:
        assert str(names) in lines[0], (str(names), lines[0])
    if says is not None:
        assert says in lines[0], (says, lines[0])
    return lines[0]


def _fingerprint(root: Path) -> dict[str, tuple]:
    """Every file and folder under ``root`` with its inode, size and modification time
    (a write changes the time, a replacement the inode); the writer lock and reader
    leases of the stores (bookkeeping, rewritten by every open) left out."""
    prints = {}
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root)
        if any(p.startswith((".bigT-writer", ".bigT-reader")) for p in rel.parts):
            continue
        st = path.stat()
        prints[rel.as_posix()] = (st.st_ino, None if path.is_dir() else st.st_size,
                                  None if path.is_dir() else st.st_mtime_ns)
    return prints


# --- the world ------------------------------------------------------------------------

def _transport() -> np.ndarray:
    rng = np.random.default_rng(7)
    return np.diag(1.0 + rng.random(N)) + 0.02 * rng.random((N, N))


def _damaged_inputs(d: Path, A: np.ndarray) -> None:
    """Matrix files that are truncated, garbage, of strings, or not of their kind."""
    sp.save_npz(d / "a.npz", sp.csr_matrix(A))
    scipy.io.savemat(d / "a.mat", {"T": sp.csr_matrix(A)})
    scipy.io.mmwrite(d / "a.mtx", sp.coo_matrix(A))
    np.save(d / "a.npy", A)
    for ext in ("npz", "mat", "mtx", "npy"):
        raw = (d / f"a.{ext}").read_bytes()
        (d / f"trunc.{ext}").write_bytes(raw[:len(raw) // 3])
        (d / f"garbage.{ext}").write_bytes(b"\x93NUMPY not really\n" * 7)
    np.save(d / "strings.npy", np.array([["a", "b"], ["c", "d"]]))
    np.save(d / "complex.npy", A.astype(np.complex128))
    np.save(d / "cube.npy", np.ones((2, 2, 2)))
    np.savez(d / "arrays.npz", A=A)
    (d / "matrix.txt").write_text("1 2\n3 4\n")


def _bad_values(d: Path, A: np.ndarray) -> None:
    """Matrices whose values no store can hold as they are."""
    nan = A.copy()
    nan[3, 4] = np.nan
    np.save(d / "nan.npy", nan)
    huge = A.copy()
    huge[2, 1] = 1e300  # beyond float32
    np.save(d / "huge.npy", huge)
    tiny = A.astype(np.float32)
    tiny[5, 6] = np.float32(1e-42)  # subnormal in float32
    np.save(d / "subnormal.npy", tiny)


def _vectors_and_images(d: Path) -> None:
    np.savez(d / "fb.npz", f=np.ones(N))
    np.save(d / "fb_strings.npy", np.array(["x"] * N))
    np.save(d / "fb_short.npy", np.ones(N - 3))
    fb = np.ones(N)
    fb[2] = np.nan
    np.save(d / "fb_nan.npy", fb)
    np.save(d / "img.npy", np.full((H, W), 0.3))
    np.save(d / "img_3x3.npy", np.full((3, 3), 0.3))
    raw = (d / "img.npy").read_bytes()
    (d / "img_trunc.npy").write_bytes(raw[:len(raw) - 40])
    (d / "img_garbage.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"junk" * 20)
    (d / "no_images").mkdir()
    (d / "no_images" / "notes.txt").write_text("not a frame")


def _foreign_paths(d: Path) -> None:
    """What a user owns: a file and a folder an output must never replace."""
    (d / "mine.txt").write_text("keep me")
    (d / "mine").mkdir()
    (d / "mine" / "keep.txt").write_text("keep me too")
    (d / "out.npz").mkdir()  # a folder with a matrix file's name
    (d / "out.npz" / "keep.txt").write_text("keep")


def _damaged_inverses(d: Path) -> None:
    """Inverse stores whose root holds a junk record or is unreadable: the root of
    X.zarr alone, since a resume reads the record before any term."""
    junk = {
        "record_string": "junk",
        "record_list": [1, 2, 3],
        "record_no_params": {"params": 5, "term": 1},
        "history_string": "HISTORY",
        "term_word": "TERM",
    }
    for name, value in junk.items():
        (d / f"{name}.zarr").mkdir()
        root = d / f"{name}.zarr" / "zarr.json"
        shutil.copy(d / "X.zarr" / "zarr.json", root)
        j = json.loads(root.read_text())
        record = j["attributes"]["bigT_inverse"]
        if value == "HISTORY":
            record["history"] = "junk"
        elif value == "TERM":
            record["term"] = "two"
        else:
            j["attributes"]["bigT_inverse"] = value
        root.write_text(json.dumps(j))
    (d / "not_json.zarr").mkdir()
    (d / "not_json.zarr" / "zarr.json").write_text("{not json")


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A 20-pixel T.zarr (4x5 images), its 2-term inverse X.zarr, a 12-pixel store
    Y.zarr, and the damaged and foreign files of the cases."""
    d = tmp_path_factory.mktemp("world")
    A = _transport()
    from_scipy(sp.csr_array(A), d / "T.zarr", tile_size=16, dtype="float64",
               image_shape=(H, W))
    from_scipy(sp.csr_array(np.eye(12) * 2.0), d / "Y.zarr", tile_size=8,
               dtype="float64", image_shape=(3, 4))
    assert main(["invert", str(d / "T.zarr"), "-o", str(d / "X.zarr"), "--terms", "2",
                 "-q"]) == 0
    _damaged_inputs(d, A)
    _bad_values(d, A)
    _vectors_and_images(d)
    _foreign_paths(d)
    _damaged_inverses(d)
    return d


# --- the file walk --------------------------------------------------------------------

@dataclass(frozen=True)
class Case:
    """``bigT argv`` (``{d}`` is the world) must fail naming ``names`` (a path under
    the world; None for no file) and, when given, saying ``says``."""

    argv: str
    names: str | None = None
    says: str | None = None

    def command(self, d: Path) -> list[str]:
        return self.argv.format(d=d).split()


_INV = "invert {d}/T.zarr -o {d}/new.zarr -q"
_COMP = "compensate {d}/X.zarr {d}/img.npy -o {d}/c.npy -q"
_BOUNCES = "bounces {d}/T.zarr {d}/X.zarr {d}/img.npy -o {d}/parts -q"

FILE_CASES = {
    # convert: truncated, garbage, mistyped inputs; values a store cannot hold
    **{f"convert {stem}.{ext}": Case(f"convert {{d}}/{stem}.{ext} -o {{d}}/new.zarr",
                                     f"{stem}.{ext}")
       for stem in ("trunc", "garbage") for ext in ("npz", "mat", "mtx", "npy")},
    "convert strings.npy": Case("convert {d}/strings.npy -o {d}/new.zarr", "strings.npy",
                                "not real numbers"),
    "convert complex.npy": Case("convert {d}/complex.npy -o {d}/new.zarr", "complex.npy",
                                "not real numbers"),
    "convert 3-D .npy": Case("convert {d}/cube.npy -o {d}/new.zarr", "cube.npy", "2-D"),
    "convert .npz of arrays": Case("convert {d}/arrays.npz -o {d}/new.zarr", "arrays.npz",
                                   "not a scipy sparse matrix"),
    "convert unknown suffix": Case("convert {d}/matrix.txt -o {d}/new.zarr", "matrix.txt"),
    "convert missing input": Case("convert {d}/absent.npz -o {d}/new.zarr", "absent.npz"),
    "convert NaN names the input": Case("convert {d}/nan.npy -o {d}/new.zarr", "nan.npy",
                                        "NaN/Inf"),
    "convert overflow names the input": Case(
        "convert {d}/huge.npy -o {d}/new.zarr --dtype float32", "huge.npy", "float32"),
    "convert subnormal names the input": Case(
        "convert {d}/subnormal.npy -o {d}/new.zarr", "subnormal.npy", "subnormal"),
    "convert -o existing file": Case("convert {d}/a.npz -o {d}/mine.txt", "mine.txt"),
    "convert -o foreign folder": Case("convert {d}/a.npz -o {d}/mine", "mine"),
    # invert: --first-bounce files, outputs that are not inverses, damaged inverses
    "invert --first-bounce .npz": Case(_INV + " --first-bounce {d}/fb.npz", "fb.npz",
                                       ".npz archive"),
    "invert --first-bounce strings": Case(_INV + " --first-bounce {d}/fb_strings.npy",
                                          "fb_strings.npy"),
    "invert --first-bounce short": Case(_INV + " --first-bounce {d}/fb_short.npy",
                                        "fb_short.npy", "17 entries"),
    "invert --first-bounce NaN": Case(_INV + " --first-bounce {d}/fb_nan.npy",
                                      "fb_nan.npy", "non-finite"),
    "invert --first-bounce garbage": Case(_INV + " --first-bounce {d}/garbage.npy",
                                          "garbage.npy"),
    "invert --first-bounce missing": Case(_INV + " --first-bounce {d}/absent.npy",
                                          "absent.npy"),
    "invert T not a store": Case("invert {d}/a.npz -o {d}/new.zarr -q", "a.npz"),
    "invert -o existing file": Case("invert {d}/T.zarr -o {d}/mine.txt -q", "mine.txt"),
    "invert -o foreign folder": Case("invert {d}/T.zarr -o {d}/mine -q", "mine"),
    "invert --json a folder": Case(_INV + " --json {d}/mine", "mine"),
    **{f"invert resumes {name}": Case(f"invert {{d}}/T.zarr -o {{d}}/{name}.zarr "
                                      "--terms 2 -q", f"{name}.zarr", "damaged inverse record")
       for name in ("record_string", "record_list", "record_no_params", "history_string",
                    "term_word")},
    "invert resumes an unreadable root": Case(
        "invert {d}/T.zarr -o {d}/not_json.zarr --terms 2 -q", "not_json.zarr",
        "unreadable zarr.json"),
    # export, info, verify: not stores; outputs that are a file of another kind or a folder
    "export store is a file": Case("export {d}/a.npz -o {d}/e.npz", "a.npz"),
    "export -o existing text file": Case("export {d}/T.zarr -o {d}/mine.txt", "mine.txt"),
    "export -o a folder": Case("export {d}/T.zarr -o {d}/out.npz", "out.npz"),
    "info a file": Case("info {d}/a.npz", "a.npz"),
    "info a foreign folder": Case("info {d}/mine", "mine"),
    "verify a file": Case("verify {d}/a.npz -q", "a.npz"),
    "verify a foreign folder": Case("verify {d}/mine -q", "mine"),
    "verify a missing store": Case("verify {d}/absent.zarr -q", "absent.zarr"),
    # acquire: pattern folders without a manifest, a manifest that is not one
    "acquire build no manifest": Case("acquire build {d}/mine {d}/mine -o {d}/new.zarr -q",
                                      "mine/manifest.json", "no pattern manifest"),
    "acquire simulate no manifest": Case(
        "acquire simulate {d}/T.zarr {d}/absent -o {d}/caps --camera 8x10 -q",
        "absent", "no pattern manifest"),
    "acquire patterns -o a file": Case(
        "acquire patterns --method stripes --projector 4x4 -o {d}/mine.txt -q", "mine.txt"),
    # scene, demo: outputs that exist and are not theirs
    "scene -o existing file": Case("scene corner --size 4x5 -o {d}/mine.txt -q",
                                   "mine.txt"),
    "scene -o foreign folder": Case("scene corner --size 4x5 -o {d}/mine -q", "mine"),
    "demo --dir a file": Case("demo --dir {d}/mine.txt --size 4x5 -q", "mine.txt"),
    "demo --dir a foreign folder": Case("demo --dir {d}/mine --size 4x5 -q", "mine"),
    # compensate, relight, bounces: images and stores that do not fit
    "compensate garbage .npy": Case("compensate {d}/X.zarr {d}/garbage.npy -o {d}/c.npy -q",
                                    "garbage.npy"),
    "compensate truncated .npy": Case(
        "compensate {d}/X.zarr {d}/img_trunc.npy -o {d}/c.npy -q", "img_trunc.npy"),
    "compensate strings": Case("compensate {d}/X.zarr {d}/strings.npy -o {d}/c.npy -q",
                               "strings.npy"),
    "compensate garbage .png": Case(
        "compensate {d}/X.zarr {d}/img_garbage.png -o {d}/c.png -q", "img_garbage.png"),
    "compensate wrong image size": Case(
        "compensate {d}/X.zarr {d}/img_3x3.npy -o {d}/c.npy -q", "img_3x3.npy"),
    "compensate X a file": Case("compensate {d}/a.npz {d}/img.npy -o {d}/c.npy -q",
                                "a.npz"),
    "relight garbage image": Case("relight {d}/T.zarr {d}/garbage.npy -o {d}/r.npy -q",
                                  "garbage.npy"),
    "relight folder of no images": Case(
        "relight {d}/T.zarr {d}/no_images -o {d}/r -q", "no_images"),
    "relight image .npz": Case("relight {d}/T.zarr {d}/a.npz -o {d}/r.npy -q", "a.npz"),
    "bounces -o existing file": Case(_BOUNCES.replace("{d}/parts", "{d}/mine.txt"),
                                     "mine.txt"),
    "bounces X of another T": Case("bounces {d}/T.zarr {d}/Y.zarr {d}/img.npy -o {d}/p -q",
                                   "Y.zarr"),
    "bounces garbage image": Case(_BOUNCES.replace("img.npy", "garbage.npy"),
                                  "garbage.npy"),
    "bounces wrong image size": Case(_BOUNCES.replace("img.npy", "img_3x3.npy"),
                                     "img_3x3.npy"),
}


@pytest.mark.parametrize("case", list(FILE_CASES.values()), ids=list(FILE_CASES))
def test_bad_file_is_one_line_and_changes_nothing(world, case, capsys):
    before = _fingerprint(world)
    names = None if case.names is None else world / case.names
    _assert_one_line_error(case.command(world), capsys, names=names, says=case.says)
    assert _fingerprint(world) == before


def test_resume_with_history_entries_of_the_wrong_type(world, tmp_path, capsys):
    shutil.copytree(world / "X.zarr", tmp_path / "X.zarr")
    root = tmp_path / "X.zarr" / "zarr.json"
    j = json.loads(root.read_text())
    j["attributes"]["bigT_inverse"]["history"] = [{"term": "x", "nnz_X": "y"}]
    root.write_text(json.dumps(j))
    before = _fingerprint(tmp_path)
    _assert_one_line_error(["invert", world / "T.zarr", "-o", tmp_path / "X.zarr",
                            "--terms", "3", "-q"], capsys, names=tmp_path / "X.zarr")
    assert _fingerprint(tmp_path) == before


def test_unreachable_scheduler(world, monkeypatch, capsys):
    # port 1 on this machine only: refused at once; the client retries until timeout
    monkeypatch.setattr(config, "SCHEDULER_CONNECT_SECONDS", 0.5)
    before = _fingerprint(world)
    for argv in (_INV, _COMP):
        line = _assert_one_line_error(
            Case(argv + " --scheduler tcp://127.0.0.1:1").command(world), capsys)
        assert "tcp://127.0.0.1:1" in line
    assert _fingerprint(world) == before


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0,
                    reason="root writes through a read-only mode")
@pytest.mark.parametrize("argv", [
    "invert {d}/T.zarr -o {ro}/X.zarr -q", "convert {d}/a.npz -o {ro}/T.zarr",
    "export {d}/T.zarr -o {ro}/e.npz", "scene corner --size 4x5 -o {ro}/S.zarr -q",
    "compensate {d}/X.zarr {d}/img.npy -o {ro}/c.npy -q",
    "bounces {d}/T.zarr {d}/X.zarr {d}/img.npy -o {ro}/parts -q",
], ids=lambda a: a.split()[0])
def test_read_only_output_folder(world, tmp_path, argv, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        _assert_one_line_error(argv.format(d=world, ro=ro).split(), capsys, names=ro)
    finally:
        ro.chmod(0o755)
    assert list(ro.iterdir()) == []


# --- the boundary: OS errors from anywhere ----------------------------------------------

@pytest.mark.parametrize("code, says", [
    (errno.ENOSPC, "rerun the same command"), (errno.EROFS, "writable disk"),
    (errno.EACCES, "permissions"), (errno.EISDIR, "file name"),
    (errno.ENOTDIR, "a part of the path is a file"), (errno.EEXIST, "another path"),
    (errno.ENOENT, os.strerror(errno.ENOENT)), (errno.EIO, os.strerror(errno.EIO)),
], ids=errno.errorcode.get)
def test_os_error_is_one_line_naming_the_file(world, monkeypatch, capsys, code, says):
    def fail(path, var=None):
        raise OSError(code, os.strerror(code), str(path))

    monkeypatch.setattr(bigT.storage.convert, "load_matrix", fail)
    _assert_one_line_error(["convert", world / "a.npz", "-o", world / "new.zarr"], capsys,
                           names=world / "a.npz", says=says)


@pytest.mark.parametrize("argv, output", [
    ("convert {d}/a.npz -o {d}/full_c.zarr", "full_c.zarr"),
    ("scene corner --size 4x5 -o {d}/full_s.zarr -q", "full_s.zarr"),
    ("invert {d}/T.zarr -o {d}/full_i.zarr -q", "full_i.zarr"),
], ids=["convert", "scene", "invert"])
def test_full_disk_names_the_output_in_cli_words(world, monkeypatch, capsys, argv, output):
    """A full disk at the rename that publishes the work: the output named (not the
    hidden folder it was built in), no Python wording, the user's files kept."""
    def full(src, dst, *args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(src))

    before = {k: v for k, v in _fingerprint(world).items() if not k.startswith(output)}
    monkeypatch.setattr(os, "replace", full)
    monkeypatch.setattr(os, "rename", full)
    line = _assert_one_line_error(argv.format(d=world).split(), capsys,
                                  names=world / output)
    monkeypatch.undo()
    assert "resume=True" not in line and ".partial" not in line and ".tmp" not in line
    after = _fingerprint(world)
    assert {k: v for k, v in after.items() if k in before} == before
    shutil.rmtree(world / output, ignore_errors=True)


# --- the option walk ------------------------------------------------------------------

@pytest.mark.parametrize("command, option, value", list(_option_cases()))
def test_nonsense_option_value_is_one_line(command, option, value, capsys):
    line = _assert_one_line_error([command, f"{option}={value}"], capsys)
    assert f"argument {option}" in line or f"/{option}" in line, line


@pytest.mark.parametrize("command", sorted(_subcommands()))
def test_every_option_is_checked_and_every_subcommand_walked(command):
    """An option taking a value has a type or choices (or is known free text), and a
    subcommand has file cases: a new one fails here until it is covered."""
    for name, option, action in _valued_options():
        if name == command:
            assert action.type or action.choices or set(action.option_strings) & FREE_TEXT, \
                f"bigT {name} {option} takes any text"
    assert any(c.argv.split()[0] == command for c in FILE_CASES.values()), command


def test_bounded_values_name_their_bound(capsys):
    """Values of the right type but out of range: the limits the issue lists."""
    cases = [
        (["bounces", "--bounces", "100000"], "[0, 64]"),
        (["invert", "--workers", "0"], ">= 1"), (["invert", "--tol=-1"], ">= 0"),
        (["invert", "--memory-limit=-5GiB"], "positive memory size"),
        (["invert", "--memory-limit", "0GiB"], "positive memory size"),
        (["invert", "--memory-limit", "1e999"], "positive memory size"),
        (["invert", "--memory-limit", "-5GiB"], "--option=VALUE"),
        (["relight", "--batch", "0"], ">= 1"), (["compensate", "--cache-mb=-1"], ">= 0"),
        (["compensate", "--clip", "1,0"], "LO < HI"),
        (["export", "--max-gb", "0"], "> 0"), (["convert", "--tile-size", "0"], ">= 1"),
        (["scene", "corner", "--albedo", "1"], "(0, 1)"),
        (["scene", "corner", "--size", "0x5"], "at least 1 pixel"),
        (["invert", "--scheduler", "local:0"], "N >= 1"),
        (["scene", "bogus"], "invalid choice"), (["bogus"], "invalid choice"),
    ]
    for argv, says in cases:
        _assert_one_line_error(argv, capsys, says=says)


@pytest.mark.parametrize("term", [10 ** 30, -3, 2.5, "2"])
def test_resume_with_a_record_naming_a_term_not_on_disk(world, tmp_path, capsys, term):
    shutil.copytree(world / "X.zarr", tmp_path / "X.zarr")
    root = tmp_path / "X.zarr" / "zarr.json"
    j = json.loads(root.read_text())
    j["attributes"]["bigT_inverse"].update(term=term, dir=term)
    root.write_text(json.dumps(j))
    before = _fingerprint(tmp_path)
    _assert_one_line_error(["invert", world / "T.zarr", "-o", tmp_path / "X.zarr",
                            "--terms", "3", "-q"], capsys, names=tmp_path / "X.zarr")
    assert _fingerprint(tmp_path) == before
