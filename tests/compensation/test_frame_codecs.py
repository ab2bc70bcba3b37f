"""The frame codecs' quick paths keep the values and the files of the reference ones:
frames read straight in float32 hold the float64 frames' values cast, bit for bit, and
float32 frames written give the files of the float64 frames (the quantisation of
before, nan_to_num then clip then rint, written out here as the reference)."""

from __future__ import annotations

import numpy as np
import pytest

from bigT.errors import ImageError
from bigT.images import ImageSource, read_image, write_image


def _reference_codes(image: np.ndarray, bits: int) -> np.ndarray:
    """The codes bigT wrote before the quick path: NaN -> 0, clipped, rounded."""
    top = 255 if bits == 8 else 65535
    scaled = np.clip(np.nan_to_num(np.asarray(image, np.float64)), 0.0, 1.0) * top
    return np.rint(scaled).astype(np.uint8 if bits == 8 else np.uint16)


@pytest.mark.parametrize("dtype, top", [(np.uint8, 255), (np.uint16, 65535)])
def test_every_code_divided_in_float32_is_the_float64_quotient_cast(dtype, top):
    codes = np.arange(top + 1, dtype=dtype)
    from bigT.images import _to_unit  # the private helper both reads go through

    quick = _to_unit(codes, "<codes>", np.float32)
    cast = (codes.astype(np.float64) / top).astype(np.float32)
    assert quick.dtype == np.float32
    assert np.array_equal(quick.view(np.uint32), cast.view(np.uint32))


@pytest.mark.parametrize("bits, colour", [(8, False), (16, False), (8, True), (16, True)])
def test_png_frames_read_in_float32_are_the_float64_frames_cast(tmp_path, bits, colour):
    rng = np.random.default_rng(bits)
    shape = (6, 7, 3) if colour else (6, 7)
    for k in range(3):
        write_image(tmp_path / f"f{k}.png", rng.uniform(0, 1, shape), bits=bits)
    source = ImageSource(tmp_path, shape[:2], 3 if colour else 1)
    for file in source.files:
        quick, reference = source.read(file, np.float32), source.read(file)
        assert quick.dtype == np.float32 and reference.dtype == np.float64
        assert np.array_equal(quick, reference.astype(np.float32))
        np.testing.assert_array_equal(reference, read_image(file, shape[:2]))


def test_float_files_read_in_float32_keep_their_checks(tmp_path):
    good = np.random.default_rng(1).uniform(-0.5, 1.5, (4, 5))
    np.save(tmp_path / "a.npy", good)
    source = ImageSource(tmp_path / "a.npy", (4, 5))
    assert np.array_equal(source.read(source.files[0], np.float32), good.astype(np.float32))
    bad = good.copy()
    bad[1, 2] = np.nan
    np.save(tmp_path / "b.npy", bad)
    with pytest.raises(ImageError, match=r"b\.npy.*1 pixel\(s\) are NaN or Inf"):
        ImageSource(tmp_path / "b.npy", (4, 5)).read(tmp_path / "b.npy", np.float32)


def test_a_frame_of_the_wrong_size_read_in_float32_names_its_file(tmp_path):
    write_image(tmp_path / "small.png", np.zeros((3, 4)), bits=16)
    source = ImageSource(tmp_path / "small.png")
    source.shape = (4, 4)  # a frame that changed after the headers were checked
    with pytest.raises(ImageError, match=r"small\.png.*does not match"):
        source.read(source.files[0], np.float32)


@pytest.mark.parametrize("bits", [8, 16])
def test_float32_frames_write_the_files_of_the_float64_frames(tmp_path, bits):
    rng = np.random.default_rng(bits)
    frame = rng.uniform(-0.2, 1.2, (9, 11)).astype(np.float32)
    frame[0, :4] = [np.nan, np.inf, -np.inf, -0.0]
    frame[1, :3] = [0.5 / 65535, 1.5 / 255, 1.0]
    single = write_image(tmp_path / "single.png", frame, bits=bits)
    double = write_image(tmp_path / "double.png", frame.astype(np.float64), bits=bits)
    assert single.read_bytes() == double.read_bytes()
    import imageio.v3 as iio

    assert np.array_equal(iio.imread(single), _reference_codes(frame, bits))


def test_float32_frames_write_the_npy_of_the_float64_frames(tmp_path):
    frame = np.random.default_rng(3).uniform(-1, 2, (5, 6)).astype(np.float32)
    a = write_image(tmp_path / "a.npy", frame)
    b = write_image(tmp_path / "b.npy", frame.astype(np.float64))
    assert a.read_bytes() == b.read_bytes()
    assert np.array_equal(np.load(a), frame)
