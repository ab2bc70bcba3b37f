"""bigT.images' PNG codecs (Pillow's decoder called directly, OpenCV's encoder and its
16-bit colour decoder) against the readers bigT used before: imageio, and ffmpeg for
16-bit colour. Same pixels, same types, writable arrays; the kinds the quick path does
not take (palettes, 1-bit, transparent colour keys) still read as imageio reads them."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image

from bigT.images import _read_deep_colour_png, read_image, read_raw_image, write_image

rng = np.random.default_rng(11)


def _pillow_png(path, array, **options):
    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG", **options)
    path.write_bytes(buffer.getvalue())
    return path


def _imageio(path):
    import imageio.v3 as iio

    return iio.imread(path)


@pytest.mark.parametrize("shape, dtype", [((9, 13), np.uint8), ((9, 13), np.uint16),
                                          ((9, 13, 2), np.uint8), ((9, 13, 3), np.uint8),
                                          ((9, 13, 4), np.uint8)])
def test_pillow_kinds_read_as_imageio_reads_them(tmp_path, shape, dtype):
    top = np.iinfo(dtype).max
    p = _pillow_png(tmp_path / "a.png", rng.integers(0, top + 1, shape).astype(dtype))
    got, expected = read_raw_image(p), _imageio(p)
    assert got.dtype == expected.dtype and got.shape == expected.shape
    assert np.array_equal(got, expected) and got.flags.writeable


@pytest.mark.parametrize("channels", [3, 4])
def test_16_bit_colour_reads_as_ffmpeg_reads_it(tmp_path, channels):
    pixels = rng.integers(0, 65536, (9, 13, channels)).astype(np.uint16)
    import cv2

    ok, data = cv2.imencode(".png", cv2.cvtColor(
        pixels, cv2.COLOR_RGB2BGR if channels == 3 else cv2.COLOR_RGBA2BGRA))
    p = tmp_path / "deep.png"
    p.write_bytes(data.tobytes())
    got = read_raw_image(p)
    assert got.dtype == np.uint16 and got.flags.writeable
    assert np.array_equal(got, pixels) and np.array_equal(got, _read_deep_colour_png(p))


@pytest.mark.parametrize("kind", ["palette", "1-bit", "grey key", "colour key"])
def test_other_kinds_read_as_imageio_reads_them(tmp_path, kind):
    grey = rng.integers(0, 256, (9, 13)).astype(np.uint8)
    colour = rng.integers(0, 256, (9, 13, 3)).astype(np.uint8)
    image, options = {"palette": (Image.fromarray(grey).convert("P"), {}),
                      "1-bit": (Image.fromarray(grey > 128), {}),
                      "grey key": (Image.fromarray(grey), {"transparency": 5}),
                      "colour key": (Image.fromarray(colour), {"transparency": (1, 2, 3)})}[kind]
    p = tmp_path / "k.png"
    image.save(p, **options)
    got, expected = read_raw_image(p), _imageio(p)
    assert got.dtype == expected.dtype and np.array_equal(got, expected)


@pytest.mark.parametrize("shape", [(9, 13), (9, 13, 3)])
@pytest.mark.parametrize("bits", [8, 16])
def test_written_pngs_hold_the_levels_read_by_an_independent_decoder(tmp_path, shape, bits):
    values = rng.uniform(-0.1, 1.1, shape)
    p = write_image(tmp_path / "w.png", values, bits=bits)
    top = 2 ** bits - 1
    levels = np.rint(np.clip(values, 0, 1) * top)
    independent = (_read_deep_colour_png(p) if bits == 16 and len(shape) == 3
                   else _imageio(p))  # ffmpeg for 16-bit colour: Pillow reads 8 bits of it
    assert independent.dtype == (np.uint8 if bits == 8 else np.uint16)
    assert np.array_equal(independent, levels)
    np.testing.assert_allclose(read_image(p), levels / top, rtol=0, atol=0)


def test_a_damaged_png_is_one_line_naming_it(tmp_path):
    from bigT.errors import ImageError

    p = write_image(tmp_path / "broken.png", rng.uniform(0, 1, (30, 40)))
    data = p.read_bytes()
    p.write_bytes(data[:60] + bytes(len(data) - 60))
    with pytest.raises(ImageError) as err:
        read_image(p)
    assert "broken.png" in str(err.value) and "\n" not in str(err.value)


def test_a_damaged_16_bit_colour_png_is_one_line_and_nothing_on_stderr(tmp_path, capfd):
    """OpenCV reads 16-bit colour PNGs; libpng prints its own complaint on a damaged one
    before failing. bigT checks the chunks first: one line naming the file, a quiet
    stderr."""
    from bigT.errors import ImageError

    p = write_image(tmp_path / "deep.png", rng.uniform(0, 1, (30, 40, 3)), bits=16)
    data = bytearray(p.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 40] = bytes(40)
    p.write_bytes(bytes(data))
    capfd.readouterr()
    with pytest.raises(ImageError, match="damaged PNG") as err:
        read_image(p)
    assert "deep.png" in str(err.value) and "\n" not in str(err.value)
    assert capfd.readouterr().err == ""
