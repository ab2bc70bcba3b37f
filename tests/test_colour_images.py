"""Colour images (issue #28, point 5): RGB files in and out of bigT.images exact to their
quantisation, grey/colour mismatches refused in one line naming the file, alpha, and the
image encoding of bigT.colour against the sRGB standard's numbers."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest

from bigT import colour
from bigT.errors import ImageError
from bigT.images import (ImageSink, ImageSource, check_image, image_encoding, png_bits,
                         read_image, read_raw_image, stored_type, write_image)

H, W = 6, 7


@pytest.fixture
def rgb():
    return np.random.default_rng(1).uniform(0, 1, (H, W, 3))


def _iio():
    import imageio.v3 as iio

    return iio


def _ffmpeg_png(path, pixels, pix_fmt):
    """Write an (H, W, C) uint16 image as a 16-bit PNG with ffmpeg (Pillow cannot)."""
    import imageio_ffmpeg

    h, w = pixels.shape[:2]
    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-loglevel", "error", "-f", "rawvideo",
                    "-pix_fmt", pix_fmt, "-s", f"{w}x{h}", "-i", "-", "-frames:v", "1",
                    "-y", str(path)], input=pixels.astype("<u2").tobytes(), check=True)


# --- encodings --------------------------------------------------------------------------

def test_srgb_against_the_standards_numbers():
    """IEC 61966-2-1: the knee at 0.04045 (encoded), slope 12.92, 2.4 power, 0.055."""
    assert colour.decode(0.5, "srgb") == pytest.approx(0.21404114048223255, abs=1e-15)
    assert colour.decode(0.04045, "srgb") == pytest.approx(0.04045 / 12.92, abs=1e-17)
    assert colour.decode(0.05, "srgb") == pytest.approx(((0.05 + 0.055) / 1.055) ** 2.4,
                                                        rel=1e-15)
    assert colour.encode(0.5, "srgb") == pytest.approx(0.7353569830524495, abs=1e-15)
    assert colour.encode(0.0031308, "srgb") == pytest.approx(0.0031308 * 12.92, rel=1e-15)
    assert colour.encode(0.0032, "srgb") == pytest.approx(1.055 * 0.0032 ** (1 / 2.4) - 0.055,
                                                          rel=1e-15)
    np.testing.assert_array_equal(colour.decode([0.0, 1.0], "srgb"), [0.0, 1.0])
    np.testing.assert_allclose(colour.encode([0.0, 1.0], "srgb"), [0.0, 1.0], atol=2e-16)


def test_srgb_round_trip_exact_on_the_real_line():
    """Either way round to float rounding, below 0, around the knees and above 1 (an
    unclipped simulated image); but light within the standard's own gap between its two
    parts (linear 0.0031308050 to 0.0031308073), which comes back to 2.4e-9."""
    v = np.concatenate([np.linspace(-0.5, 2.0, 100_001),
                        np.linspace(0.04044, 0.04046, 1001),     # the encoded knee
                        np.linspace(0.0031307, 0.0031309, 1001)])  # the linear knee
    there = colour.encode(colour.decode(v, "srgb"), "srgb")
    back = colour.decode(colour.encode(v, "srgb"), "srgb")
    np.testing.assert_allclose(there, v, rtol=1e-14, atol=1e-16)
    gap = (v > 0.04045 / 12.92) & (v <= 0.0031308073)
    np.testing.assert_allclose(back[~gap], v[~gap], rtol=1e-14, atol=1e-16)
    np.testing.assert_allclose(back[gap], v[gap], rtol=0, atol=2.4e-9)
    assert np.all(np.diff(colour.decode(np.sort(v), "srgb")) >= 0)  # monotone


def test_every_8_and_16_bit_level_survives_decode_and_encode():
    for top in (255, 65535):
        levels = np.arange(top + 1)
        back = colour.encode(colour.decode(levels / top, "srgb"), "srgb")
        np.testing.assert_array_equal(np.rint(back * top), levels)


def test_linear_is_the_identity_and_a_copy():
    v = np.array([[-0.2, 0.3, 1.4]])
    out = colour.decode(v, "linear")
    np.testing.assert_array_equal(out, v)
    assert out is not v and not np.shares_memory(out, v)
    np.testing.assert_array_equal(colour.encode(v, "linear"), v)


def test_unknown_encoding_names_the_known_ones():
    with pytest.raises(ImageError, match="'gamma22'.*srgb or linear"):
        colour.decode(0.5, "gamma22")


@pytest.mark.parametrize("bits, channels, requested, expected", [
    (8, 3, None, "srgb"),          # an 8-bit colour photograph
    (np.uint8, 3, None, "srgb"),
    (8, 3, "linear", "linear"),    # unless told otherwise
    (16, 3, None, "linear"),
    ("uint16", 3, None, "linear"),
    (np.float32, 3, None, "linear"),
    (None, 3, None, "linear"),     # floats (or not known)
    (8, 1, None, "linear"),        # grey stays as it always was
    (16, 3, "srgb", "srgb"),
])
def test_default_encoding_policy(bits, channels, requested, expected):
    assert colour.default_encoding(bits, channels, requested) == expected


# --- round trips ------------------------------------------------------------------------

def test_png8_rgb_round_trip(tmp_path, rgb):
    p = write_image(tmp_path / "a.png", rgb, bits=8)
    raw = _iio().imread(p)
    assert raw.dtype == np.uint8 and raw.shape == (H, W, 3)
    np.testing.assert_array_equal(read_image(p), np.round(rgb * 255) / 255)
    assert png_bits(p) == 8


def test_png16_rgb_round_trip_keeps_all_16_bits(tmp_path, rgb):
    """Pillow reads a 16-bit RGB PNG as 8 bits: bigT must not."""
    p = write_image(tmp_path / "a.png", rgb, bits=16)
    back = read_image(p)
    assert back.shape == (H, W, 3)
    np.testing.assert_array_equal(back, np.round(rgb * 65535) / 65535)
    raw = read_raw_image(p)
    assert raw.dtype == np.uint16 and np.any(raw % 257 != 0)  # not 8 bits scaled up
    assert png_bits(p) == 16 and stored_type(p) == np.uint16


def test_png16_rgba_opaque_read_with_all_bits(tmp_path):
    px = np.random.default_rng(2).integers(0, 65536, (H, W, 4)).astype(np.uint16)
    px[..., 3] = 65535
    _ffmpeg_png(tmp_path / "a.png", px, "rgba64le")
    np.testing.assert_array_equal(read_image(tmp_path / "a.png"), px[..., :3] / 65535)


@pytest.mark.parametrize("dtype, top", [(np.uint8, 255), (np.uint16, 65535)])
def test_integer_rgb_tiff_read_scaled(tmp_path, dtype, top):
    px = np.random.default_rng(3).integers(0, top + 1, (H, W, 3)).astype(dtype)
    _iio().imwrite(tmp_path / "a.tif", px)
    np.testing.assert_array_equal(read_image(tmp_path / "a.tif"), px / top)
    assert stored_type(tmp_path / "a.tif") == dtype


@pytest.mark.parametrize("suffix", [".tif", ".tiff", ".npy"])
def test_float_rgb_round_trip_unclipped(tmp_path, rgb, suffix):
    data = rgb * 1.7 - 0.2
    p = write_image(tmp_path / f"a{suffix}", data)
    back = read_image(p)
    assert back.shape == (H, W, 3)
    np.testing.assert_array_equal(back, data.astype(np.float32))


def test_grey_and_colour_folder_batches(tmp_path, rgb):
    for i in range(3):
        write_image(tmp_path / "in" / f"f{i}.png", rgb * (i + 1) / 3, bits=8)
    source = ImageSource(tmp_path / "in", shape=(H, W), channels=3)
    assert source.frame_shape == (H, W, 3)
    sink = ImageSink(tmp_path / "out", source)
    assert sink.channels == 3
    shapes = []
    for files, frames in source.batches(2):
        shapes.append(frames.shape)
        sink.write(files, frames)
    assert shapes == [(2, H, W, 3), (1, H, W, 3)]
    for i in range(3):  # 8 bits in, 8 bits out: the same file values
        np.testing.assert_array_equal(read_image(tmp_path / "out" / f"f{i}.png"),
                                      read_image(tmp_path / "in" / f"f{i}.png"))
        assert png_bits(tmp_path / "out" / f"f{i}.png") == 8


# --- refusals ---------------------------------------------------------------------------

def test_a_folder_with_one_frame_of_the_other_kind_is_refused_when_opened(tmp_path, rgb):
    """From the headers, before any frame is read or output written (compensate writes
    a folder frame by frame)."""
    for i in range(3):
        write_image(tmp_path / "grey" / f"f{i}.png", rgb[..., 0])
        write_image(tmp_path / "colour" / f"f{i}.png", rgb)
    write_image(tmp_path / "grey" / "f9.png", rgb)
    write_image(tmp_path / "colour" / "f9.tif", rgb[..., 0])
    with pytest.raises(ImageError, match=r"f9\.png: colour image .* given to a grey transport"):
        ImageSource(tmp_path / "grey", (H, W))
    with pytest.raises(ImageError, match=r"f9\.tif: grey image .* given to a colour transport"):
        ImageSource(tmp_path / "colour", (H, W), channels=3)
    with pytest.raises(ImageError, match=r"f9\.tif: grey image"):  # size unknown: channels
        ImageSource(tmp_path / "colour", channels=3)


def _one_line(exc_info) -> str:
    text = str(exc_info.value)
    assert "\n" not in text
    return text


def test_grey_image_to_a_colour_transport_refused_in_one_line(tmp_path, rgb):
    p = write_image(tmp_path / "grey.png", rgb[..., 0])
    with pytest.raises(ImageError) as e:
        read_image(p, (H, W), channels=3)
    assert _one_line(e).startswith(f"{p}: grey image ({H}, {W}) given to a colour transport "
                                   "(3 channels)")
    assert "give an RGB image" in str(e.value)
    with pytest.raises(ImageError, match="grey.png: grey image"):
        ImageSource(p, (H, W), channels=3).read_all()


def test_colour_image_to_a_grey_transport_refused_in_one_line(tmp_path, rgb):
    p = write_image(tmp_path / "rgb.tif", rgb)
    with pytest.raises(ImageError) as e:
        read_image(p, (H, W), channels=1)
    assert _one_line(e).startswith(f"{p}: colour image ({H}, {W}, 3) (3 channels) given to "
                                   "a grey transport (1 channel)")
    assert "convert it to grey" in str(e.value)


def test_alpha_dropped_only_when_opaque(tmp_path, rgb):
    iio = _iio()
    px = np.round(rgb * 255).astype(np.uint8)
    iio.imwrite(tmp_path / "opaque.png", np.dstack([px, np.full((H, W), 255, np.uint8)]))
    np.testing.assert_array_equal(read_image(tmp_path / "opaque.png", channels=3), px / 255)
    iio.imwrite(tmp_path / "la.png", np.dstack([px[..., 0], np.full((H, W), 255, np.uint8)]))
    np.testing.assert_array_equal(read_image(tmp_path / "la.png", channels=1), px[..., 0] / 255)
    alpha = np.full((H, W), 255, np.uint8)
    alpha[2, 3] = alpha[0, 0] = 128
    iio.imwrite(tmp_path / "see.png", np.dstack([px, alpha]))
    with pytest.raises(ImageError) as e:
        read_image(tmp_path / "see.png")
    assert "see.png: image with transparency (2 pixel(s) not fully opaque)" in _one_line(e)
    np.testing.assert_array_equal(  # floats: opaque is 1.0
        check_image(np.dstack([rgb, np.ones((H, W))])), rgb)


def test_other_channel_counts_refused(tmp_path):
    np.save(tmp_path / "five.npy", np.zeros((H, W, 5)))
    with pytest.raises(ImageError, match=r"five\.npy: image with 5 channels; bigT reads grey"):
        read_image(tmp_path / "five.npy")
    with pytest.raises(ImageError, match="1 \\(grey\\) or 3 \\(RGB\\) channels, not 2"):
        ImageSource(tmp_path / "five.npy", channels=2)


def test_colour_nan_and_size_refused(tmp_path, rgb):
    bad = rgb.copy()
    bad[1, 1, 2] = np.nan
    np.save(tmp_path / "nan.npy", bad)
    with pytest.raises(ImageError, match=r"nan\.npy: 1 value\(s\) are NaN or Inf"):
        read_image(tmp_path / "nan.npy")
    p = write_image(tmp_path / "rgb.png", rgb)
    with pytest.raises(ImageError, match=rf"rgb\.png.*\({H}, {W}\).*\({H + 1}, {W}\)"):
        read_image(p, (H + 1, W), channels=3)


def test_forged_colour_header_refused_before_decoding(tmp_path):
    """A .npy header declaring more than H W x 4 values, with no data behind it."""
    path = tmp_path / "huge.npy"
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(
            f, {"shape": (H, W, 5000), "fortran_order": False, "descr": "<f8"})
    with pytest.raises(ImageError, match=r"huge\.npy: the header declares .*refused before"):
        read_image(path, (H, W), channels=3)


def test_float_rgb_tiff_header_read_without_pillow(tmp_path, rgb):
    """Pillow cannot parse an RGB float TIFF's header; tifffile's reading of it keeps
    the header check in force for that format too."""
    from bigT.images import declared_shape

    p = write_image(tmp_path / "f.tif", rgb)
    assert declared_shape(p) == (H, W, 3)
    with pytest.raises(ImageError, match="far larger"):
        read_image(p, (2, 2))


def test_write_refuses_other_shapes(tmp_path):
    with pytest.raises(ImageError, match=r"grey \(H, W\) or RGB \(H, W, 3\)"):
        write_image(tmp_path / "x.png", np.zeros((H, W, 4)))


# --- the encoding of a file -------------------------------------------------------------

def test_image_encoding_of_files(tmp_path, rgb):
    png8 = write_image(tmp_path / "c8.png", rgb, bits=8)
    png16 = write_image(tmp_path / "c16.png", rgb, bits=16)
    grey8 = write_image(tmp_path / "g8.png", rgb[..., 0], bits=8)
    tif = write_image(tmp_path / "c.tif", rgb)
    npy = write_image(tmp_path / "c.npy", rgb)
    assert image_encoding(png8, 3) == "srgb"
    assert image_encoding(png8, 3, "linear") == "linear"
    assert image_encoding(png16, 3) == "linear"
    assert image_encoding(grey8, 1) == "linear"
    assert image_encoding(tif, 3) == "linear" and image_encoding(npy, 3) == "linear"
    assert stored_type(npy) == np.float32
