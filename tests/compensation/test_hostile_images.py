"""Hostile image and video files (issue #33, item 4): a small file whose header declares
a huge image is refused from its header, before decoding, in one line with no library
warning and in bounded memory; an unreadable video's error says what ffmpeg found wrong,
not ffmpeg's version banner."""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import warnings
import zlib
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from bigT import config
from bigT.cli import main
from bigT.compensation.video import VideoSink, VideoSource
from bigT.errors import ImageError
from bigT.images import declared_shape, read_image, write_image
from bigT.storage import from_scipy

REPO = Path(__file__).resolve().parents[2]
#: What the issue measured: a 164 KB PNG declaring 13000 x 13000 cost 1.8 GB.
HUGE = 13000


def forged_png(path: Path, height: int, width: int) -> Path:
    """A valid 1x1 16-bit gray PNG whose IHDR is rewritten to declare ``height`` x
    ``width`` (its CRC recomputed, so every reader takes the header as valid)."""
    write_image(path, np.full((1, 1), 0.5), bits=16)
    raw = bytearray(path.read_bytes())
    assert raw[12:16] == b"IHDR"
    raw[16:24] = struct.pack(">II", width, height)
    raw[29:33] = struct.pack(">I", zlib.crc32(bytes(raw[12:29])))
    path.write_bytes(bytes(raw))
    return path


def compressible_png(path: Path, height: int, width: int) -> Path:
    """A real, valid 8-bit gray PNG of zeros, ``height`` x ``width``, compressed at
    zlib level 9 row by row (never held whole): 13000 x 13000 is the issue's 164 KB."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data)))

    deflate, row = zlib.compressobj(9), b"\0" * (width + 1)  # filter byte 0, then pixels
    idat = b"".join([deflate.compress(row) for _ in range(height)] + [deflate.flush()])
    path.write_bytes(b"\x89PNG\r\n\x1a\n"
                     + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
                     + chunk(b"IDAT", idat) + chunk(b"IEND", b""))
    return path


def forged_npy(path: Path, shape: tuple) -> Path:
    """A .npy header declaring ``shape`` float64, followed by 8 bytes of data."""
    header = np.lib.format.header_data_from_array_1_0(np.zeros(1))
    header["shape"] = shape
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(f, header)
        f.write(b"\0" * 8)
    return path


def test_forged_headers_are_read_without_decoding(tmp_path):
    """The declared shape is what the header says (Pillow's own parser agrees on the
    PNG: its checksums pass)."""
    from PIL import Image

    png = forged_png(tmp_path / "huge.png", HUGE, HUGE + 1)
    assert declared_shape(png) == (HUGE, HUGE + 1)
    with warnings.catch_warnings():  # Pillow's own size warning: not under test here
        warnings.simplefilter("ignore")
        with Image.open(png) as im:  # an independent reader of the same header
            assert im.size == (HUGE + 1, HUGE)
    assert declared_shape(forged_npy(tmp_path / "huge.npy", (HUGE, HUGE))) == (HUGE, HUGE)


@pytest.mark.parametrize("shape", [(96, 128), None], ids=["store shape", "no shape"])
@pytest.mark.parametrize("kind", ["png", "npy"])
def test_huge_header_refused_before_decoding(tmp_path, kind, shape):
    path = (forged_png(tmp_path / "huge.png", HUGE, HUGE) if kind == "png"
            else forged_npy(tmp_path / "huge.npy", (HUGE, HUGE)))
    says = "transport's image shape (96, 128)" if shape else "IMAGE_MAX_VALUES"
    with pytest.raises(ImageError, match=rf"huge\.{kind}: the header declares .*13000.*"
                       + says.replace("(", r"\(").replace(")", r"\)")):
        read_image(path, shape)
    assert HUGE * HUGE > config.IMAGE_MAX_VALUES  # refused by the cap, without a shape


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="VmHWM is Linux's")
def test_huge_png_through_the_command_line_is_one_line_in_bounded_memory(tmp_path):
    """The issue's case: ``bigT compensate`` of a real 164 KB PNG of 13000 x 13000, in a
    process of its own whose peak memory is measured: one line on stderr (no Pillow
    warning), exit 2, and a peak far below what decoding it costs (measured before this
    check: 1.53 GB peak, 11 s, and Pillow's DecompressionBombWarning on stderr)."""
    n = 96 * 128
    from_scipy(sp.identity(n, format="csr"), tmp_path / "X.zarr", image_shape=(96, 128),
               tile_size=4096)
    assert compressible_png(tmp_path / "huge.png", HUGE, HUGE).stat().st_size < 200_000
    # the peak of this process's own memory (VmHWM): ru_maxrss would count the forked
    # test process's memory too, which Linux carries across exec
    script = (
        "import json, re, sys\n"
        "from bigT.cli import main\n"
        "status = main(sys.argv[1:])\n"
        "from pathlib import Path\n"
        "status_file = Path('/proc/self/status').read_text()\n"
        "peak = int(re.search(r'VmHWM:\\s*(\\d+) kB', status_file).group(1)) * 1024\n"
        "print(json.dumps({'status': status, 'peak': peak}))\n")
    run = subprocess.run(
        [sys.executable, "-W", "default", "-c", script, "compensate", str(tmp_path / "X.zarr"),
         str(tmp_path / "huge.png"), "-o", str(tmp_path / "out.png"), "-q"],
        capture_output=True, text=True, cwd=REPO, timeout=300,
        env={**os.environ, "PYTHONPATH": str(REPO)})
    result = json.loads(run.stdout.strip().splitlines()[-1])
    lines = [line for line in run.stderr.splitlines() if line.strip()]
    assert result["status"] == 2, run.stderr
    assert len(lines) == 1, run.stderr
    assert "huge.png: the header declares an image of shape (13000, 13000)" in lines[0]
    assert "Warning" not in run.stderr and "decompression bomb" not in run.stderr
    # the interpreter with numpy, scipy and zarr peaks at ~80 MB here; decoding the
    # image would add its 169 MB of pixels and their float64 copy (1.35 GB)
    assert result["peak"] < 400 << 20, result
    assert not (tmp_path / "out.png").exists()


def test_a_folder_with_one_huge_frame_is_refused_before_anything_is_written(tmp_path, capsys):
    from_scipy(sp.identity(12, format="csr"), tmp_path / "X.zarr", image_shape=(3, 4),
               tile_size=8)
    frames = tmp_path / "frames"
    frames.mkdir()
    write_image(frames / "a.png", np.full((3, 4), 0.2), bits=8)
    forged_png(frames / "b.png", HUGE, HUGE)
    assert main(["compensate", str(tmp_path / "X.zarr"), str(frames), "-o",
                 str(tmp_path / "out"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "b.png: the header declares" in err, err
    assert not (tmp_path / "out").exists()


# --- video ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def good_mp4(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("video") / "good.mp4"
    with VideoSink(path, (32, 48), 10.0) as sink:
        sink.write(np.random.default_rng(0).random((20, 32, 48)))
    return path


def _damaged(good: Path, tmp_path: Path) -> dict[str, Path]:
    data = good.read_bytes()
    rng = np.random.default_rng(1)
    files = {"truncated": data[:len(data) // 2], "header only": data[:600],
             "garbage": rng.integers(0, 256, 5000, dtype=np.uint8).tobytes(), "empty": b""}
    out = {}
    for name, raw in files.items():
        out[name] = tmp_path / f"{name.replace(' ', '_')}.mp4"
        out[name].write_bytes(raw)
    return out


def test_an_unreadable_video_names_the_cause_not_the_banner(good_mp4, tmp_path):
    for name, path in _damaged(good_mp4, tmp_path).items():
        with pytest.raises(ImageError) as caught:
            VideoSource(path)
        text = str(caught.value)
        assert text.startswith(f"{path}: cannot read the video ("), (name, text)
        assert "\n" not in text
        for banner in ("ffmpeg version", "configuration", "built with", "libav", "==="):
            assert banner not in text, (name, text)
        # an mp4 cut before its index (moov atom): ffmpeg's own word for what is missing
        assert "moov atom not found" in text or "Invalid data" in text, (name, text)


def test_the_cause_through_the_command_line(good_mp4, tmp_path, capsys):
    from_scipy(sp.identity(32 * 48, format="csr"), tmp_path / "X.zarr", image_shape=(32, 48),
               tile_size=2048)
    bad = _damaged(good_mp4, tmp_path)["truncated"]
    assert main(["compensate", str(tmp_path / "X.zarr"), str(bad), "-o",
                 str(tmp_path / "out.mp4"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "moov atom not found" in err, err
    assert "ffmpeg version" not in err
