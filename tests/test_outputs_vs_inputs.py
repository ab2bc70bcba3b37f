"""Outputs never destroy inputs (issue #33, item 4): every command that writes, and
the library calls behind them, refuse an output that is one of their inputs (after
symbolic links, ``..`` and hard links), lies inside an input folder or store, or holds
an input it would replace: one line naming both paths, exit status 2, and nothing on
disk changed. Outputs beside their inputs (the ordinary case) still work."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from bigT.atomic import refuse_overwriting_inputs
from bigT.cli import main
from bigT.compensation import FileCompensation
from bigT.compensation.video import VideoSink
from bigT.errors import OutputError
from bigT.images import ImageSink, ImageSource, read_image, write_image
from bigT.storage import from_scipy

H, W = 4, 5
N = H * W


# --- the world ----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    """T.zarr and its inverse X.zarr (4x5 images), an image, a folder of frames, a
    video, a matrix file, a first-bounce vector, and links to the image."""
    d = tmp_path_factory.mktemp("world")
    rng = np.random.default_rng(3)
    A = np.eye(N) + 0.05 * rng.random((N, N))
    sp.save_npz(d / "T.npz", sp.csr_array(A))
    from_scipy(sp.csr_array(A), d / "T.zarr", tile_size=8, image_shape=(H, W))
    assert main(["invert", str(d / "T.zarr"), "-o", str(d / "X.zarr"), "--terms", "1",
                 "-q"]) == 0
    write_image(d / "img.png", rng.random((H, W)) * 0.5, bits=16)
    write_image(d / "bounce_0.tif", rng.random((H, W)) * 0.5)
    (d / "frames").mkdir()
    for k in range(2):
        write_image(d / "frames" / f"f{k}.png", rng.random((H, W)) * 0.5, bits=8)
    with VideoSink(d / "movie.mkv", (H, W), 10.0) as video:
        video.write(rng.random((3, H, W)))
    for name in ("p_seen.png", "q_compare.png"):  # named as compensate --simulate's outputs
        write_image(d / name, rng.random((H, W)) * 0.5, bits=16)
    np.save(d / "fb.npy", np.ones(N))
    os.symlink(d / "img.png", d / "link.png")
    os.link(d / "img.png", d / "hard.png")
    (d / "sub").mkdir()
    np.save(d / "sub" / "fb.npy", np.ones(N))
    return d


def _fingerprint(root: Path) -> dict[str, tuple]:
    """Every path under ``root`` (links not followed): inode, size, modification time
    and, for files, their bytes."""
    prints = {}
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root).as_posix()
        if any(part.startswith(".bigT-") for part in Path(rel).parts):
            continue  # locks and reader leases: bookkeeping, not data
        st = path.lstat()
        data = path.read_bytes() if path.is_file() and not path.is_symlink() else None
        prints[rel] = (st.st_ino, st.st_size, st.st_mtime_ns, data)
    return prints


def _refused(argv: str, d: Path, capsys, output: str, input_: str, says: str) -> None:
    """``bigT argv`` exits 2 with one line naming ``output`` and ``input_`` (paths under
    ``d``) and saying ``says``; nothing under ``d`` changes."""
    before = _fingerprint(d)
    status = main(argv.format(d=d).split())
    out, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if line.strip()]
    assert status == 2, (status, out, err)
    assert len(lines) == 1, err
    assert f"{d / output}: " in lines[0] and str(d / input_) in lines[0], lines[0]
    assert says in lines[0], lines[0]
    assert _fingerprint(d) == before, "a refused command changed what was on disk"


_COMP = "compensate {d}/X.zarr"
_SAME = "is the input"
_INSIDE = "lies inside the input"
_HOLDS = "holds the input"

CASES = {
    # compensate: an image, a folder, a video, through links, into a store
    "image onto itself": (f"{_COMP} {{d}}/img.png -o {{d}}/img.png", "img.png", "img.png", _SAME),
    "image through ..": (f"{_COMP} {{d}}/img.png -o {{d}}/sub/../img.png", "sub/../img.png",
                         "img.png", _SAME),
    "image onto a symlink to it": (f"{_COMP} {{d}}/img.png -o {{d}}/link.png", "link.png",
                                   "img.png", _SAME),
    "image onto a hard link to it": (f"{_COMP} {{d}}/img.png -o {{d}}/hard.png", "hard.png",
                                     "img.png", _SAME),
    "image into its folder by name": (f"{_COMP} {{d}}/img.png -o {{d}}", "img.png", "img.png",
                                      _SAME),
    "image into the store X": (f"{_COMP} {{d}}/img.png -o {{d}}/X.zarr/img.png",
                               "X.zarr/img.png", "X.zarr", _INSIDE),
    "folder onto itself": (f"{_COMP} {{d}}/frames -o {{d}}/frames", "frames", "frames", _SAME),
    "folder into itself": (f"{_COMP} {{d}}/frames -o {{d}}/frames/out", "frames/out", "frames",
                           _INSIDE),
    "folder to a video inside it": (f"{_COMP} {{d}}/frames -o {{d}}/frames/m.mkv",
                                    "frames/m.mkv", "frames", _INSIDE),
    "video onto itself": (f"{_COMP} {{d}}/movie.mkv -o {{d}}/movie.mkv", "movie.mkv",
                          "movie.mkv", _SAME),
    "simulate's seen image onto the input": (
        f"{_COMP} {{d}}/p_seen.png -o {{d}}/p.png --simulate {{d}}/T.zarr",
        "p_seen.png", "p_seen.png", _SAME),
    "simulate's figure onto the input": (
        f"{_COMP} {{d}}/q_compare.png -o {{d}}/q.png --simulate {{d}}/T.zarr",
        "q_compare.png", "q_compare.png", _SAME),
    # relight, bounces
    "relight onto itself": ("relight {d}/T.zarr {d}/img.png -o {d}/img.png", "img.png",
                            "img.png", _SAME),
    "relight into T": ("relight {d}/T.zarr {d}/frames -o {d}/T.zarr/frames", "T.zarr/frames",
                       "T.zarr", _INSIDE),
    "bounces over their input": ("bounces {d}/T.zarr {d}/X.zarr {d}/bounce_0.tif -o {d}",
                                 "bounce_0.tif", "bounce_0.tif", _SAME),
    "bounces into X": ("bounces {d}/T.zarr {d}/X.zarr {d}/img.png -o {d}/X.zarr/parts",
                       "X.zarr/parts", "X.zarr", _INSIDE),
    # export, convert
    "export into the store": ("export {d}/T.zarr -o {d}/T.zarr/T.npz", "T.zarr/T.npz",
                              "T.zarr", _INSIDE),
    "export over the store": ("export {d}/T.zarr -o {d}/T.zarr", "T.zarr", "T.zarr", _SAME),
    "convert onto its input": ("convert {d}/T.npz -o {d}/T.npz --overwrite", "T.npz", "T.npz",
                               _SAME),
    "convert over the folder of its input": ("convert {d}/sub/../T.npz -o {d} --overwrite", "",
                                             "sub/../T.npz", _HOLDS),
    # invert: the output, its --json and --first-bounce against T
    "invert onto T": ("invert {d}/T.zarr -o {d}/T.zarr --overwrite", "T.zarr", "T.zarr", _SAME),
    "invert inside T": ("invert {d}/T.zarr -o {d}/T.zarr/X.zarr", "T.zarr/X.zarr", "T.zarr",
                        _INSIDE),
    "invert an inverse into itself": ("invert {d}/X.zarr -o {d}/X.zarr --overwrite", "X.zarr",
                                      "X.zarr", ""),
    "invert's report into T": ("invert {d}/T.zarr -o {d}/Y.zarr --json {d}/T.zarr/r.json",
                               "T.zarr/r.json", "T.zarr", _INSIDE),
    "invert over its first bounce": ("invert {d}/T.zarr -o {d}/fb.npy --first-bounce "
                                     "{d}/fb.npy", "fb.npy", "fb.npy", _SAME),
}


@pytest.mark.parametrize("case", CASES, ids=list(CASES))
def test_an_output_that_would_destroy_an_input_is_refused(world, case, capsys):
    argv, output, input_, says = CASES[case]
    _refused(argv + " -q", world, capsys, output, input_, says)


def test_outputs_beside_their_inputs_still_work(world, tmp_path, capsys):
    """A folder written into may hold an input it does not replace: bounces written
    into the folder of their input image, a compensated folder beside its frames."""
    d = tmp_path / "w"
    d.mkdir()
    write_image(d / "img.png", read_image(world / "img.png"), bits=16)
    assert main(["bounces", str(world / "T.zarr"), str(world / "X.zarr"), str(d / "img.png"),
                 "-o", str(d), "--bounces", "1", "-q"]) == 0
    assert (d / "bounce_0.tif").is_file() and (d / "img.png").is_file()
    assert main(["compensate", str(world / "X.zarr"), str(world / "frames"), "-o",
                 str(d / "frames"), "-q"]) == 0
    assert sorted(p.name for p in (d / "frames").iterdir()) == ["f0.png", "f1.png"]
    capsys.readouterr()


# --- the library calls --------------------------------------------------------------------

def test_library_calls_refuse_too(world):
    """A Python caller gets the same protection as the command line."""
    from bigT import stratified_inverse
    from bigT.acquisition import build_transport

    before = _fingerprint(world)
    with pytest.raises(OutputError, match="img.png: is the input .*img.png"):
        FileCompensation(world / "X.zarr", world / "img.png", world / "img.png")
    with pytest.raises(OutputError, match="movie.mkv: is the input"):
        FileCompensation(world / "X.zarr", world / "movie.mkv", world / "movie.mkv")
    with pytest.raises(OutputError, match="lies inside the input .*X.zarr"):
        FileCompensation(world / "X.zarr", world / "img.png", world / "X.zarr" / "o.png")
    with pytest.raises(OutputError, match="T.zarr: is the input"):
        stratified_inverse(world / "T.zarr", world / "T.zarr", overwrite=True)
    with pytest.raises(OutputError, match="sub: holds the input .*sub/fb.npy"):
        stratified_inverse(world / "T.zarr", world / "sub",
                           first_bounce=str(world / "sub" / "fb.npy"))
    with pytest.raises(OutputError, match="frames: is the input .*frames"):
        ImageSink(world / "frames", ImageSource(world / "frames"))
    with pytest.raises(OutputError, match="frames/T.zarr: lies inside the input .*frames"):
        build_transport(world / "sub", world / "frames", world / "frames" / "T.zarr")
    assert _fingerprint(world) == before


def test_the_rule(tmp_path):
    """refuse_overwriting_inputs on its own: what is refused, and what is not."""
    a, b = tmp_path / "a", tmp_path / "b"
    a.mkdir()
    (a / "f.png").write_bytes(b"x")
    refuse_overwriting_inputs([b / "o.png", tmp_path / "new.zarr"], [a, a / "f.png", None])
    # a folder written into may hold an input; replaced whole, it may not
    refuse_overwriting_inputs([], [a / "f.png"], folders=[a])
    with pytest.raises(OutputError, match=re.escape(f"{a}: holds the input {a / 'f.png'}")):
        refuse_overwriting_inputs([a], [a / "f.png"])
    with pytest.raises(OutputError, match="is the input"):
        refuse_overwriting_inputs([], [a], folders=[tmp_path / "b" / ".." / "a"])
    # a link to the folder is the folder
    os.symlink(a, tmp_path / "link")
    with pytest.raises(OutputError, match="lies inside the input"):
        refuse_overwriting_inputs([tmp_path / "link" / "g.png"], [a])
