"""Image I/O: round trips per format, folders as batches, clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from bigT.errors import ImageError
from bigT.images import (ImageSink, ImageSource, check_image, list_frames, read_image,
                         write_image)

from comp_helpers import make_store, random_transport


@pytest.fixture
def img():
    return np.random.default_rng(0).uniform(0, 1, (7, 9))


def test_png8_round_trip(tmp_path, img):
    p = write_image(tmp_path / "a.png", img, bits=8)
    import imageio.v3 as iio

    assert iio.imread(p).dtype == np.uint8
    back = read_image(p)
    np.testing.assert_allclose(back, np.round(img * 255) / 255, atol=1e-12)
    assert np.abs(back - img).max() <= 0.5 / 255 + 1e-12


def test_png16_round_trip(tmp_path, img):
    p = write_image(tmp_path / "a.png", img)
    import imageio.v3 as iio

    assert iio.imread(p).dtype == np.uint16
    np.testing.assert_allclose(read_image(p), np.round(img * 65535) / 65535, atol=1e-12)


@pytest.mark.filterwarnings("ignore:.*vendored tifffile:DeprecationWarning")
def test_integer_inputs_map_to_unit(tmp_path):
    import imageio.v3 as iio

    iio.imwrite(tmp_path / "w8.png", np.full((3, 4), 255, np.uint8))
    iio.imwrite(tmp_path / "w16.png", np.full((3, 4), 65535, np.uint16))
    iio.imwrite(tmp_path / "h16.tif", np.full((3, 4), 32768, np.uint16))
    assert np.all(read_image(tmp_path / "w8.png") == 1.0)
    assert np.all(read_image(tmp_path / "w16.png") == 1.0)
    np.testing.assert_allclose(read_image(tmp_path / "h16.tif"), 32768 / 65535)


@pytest.mark.parametrize("suffix", [".tif", ".tiff", ".npy"])
def test_float_round_trip_unclipped(tmp_path, img, suffix):
    data = img * 1.7 - 0.2  # floats are kept outside [0, 1]
    p = write_image(tmp_path / f"a{suffix}", data)
    np.testing.assert_allclose(read_image(p), data.astype(np.float32), rtol=1e-7)


def test_png_clips(tmp_path):
    p = write_image(tmp_path / "c.png", np.array([[-0.5, 0.5, 1.5]]))
    np.testing.assert_allclose(read_image(p), [[0.0, round(0.5 * 65535) / 65535, 1.0]])


def test_folder_batches_sorted(tmp_path, img):
    frames = {f"f{i:02d}.png": img * (i + 1) / 12 for i in (3, 0, 11, 7)}
    for name, f in frames.items():
        write_image(tmp_path / "in" / name, f)
    (tmp_path / "in" / "notes.txt").write_text("ignored")
    src = ImageSource(tmp_path / "in", shape=img.shape)
    assert src.is_folder and [p.name for p in src.files] == sorted(frames)
    got = [(list(map(lambda p: p.name, files)), batch.shape) for files, batch in src.batches(3)]
    assert got == [(["f00.png", "f03.png", "f07.png"], (3, 7, 9)), (["f11.png"], (1, 7, 9))]
    sink = ImageSink(tmp_path / "out", src, bits=8)
    for files, batch in src.batches(2):
        sink.write(files, batch)
    assert [p.name for p in list_frames(tmp_path / "out")] == sorted(frames)
    np.testing.assert_allclose(read_image(tmp_path / "out" / "f11.png"),
                               read_image(tmp_path / "in" / "f11.png"), atol=0.5 / 255 + 1e-12)


def test_colour_refused_by_a_grey_transport_naming_file_and_channels(tmp_path):
    """A grey transport (channels=1, what ImageSource assumes when not told) refuses a
    colour image; read_image without channels= reads it (tests/test_colour_images.py)."""
    import imageio.v3 as iio

    iio.imwrite(tmp_path / "rgb.png", np.zeros((4, 5, 3), np.uint8))
    with pytest.raises(ImageError, match=r"rgb\.png.*3 channels.*grey transport"):
        read_image(tmp_path / "rgb.png", channels=1)
    with pytest.raises(ImageError, match=r"rgb\.png.*3 channels.*grey transport"):
        ImageSource(tmp_path / "rgb.png").read_all()
    np.save(tmp_path / "one.npy", np.zeros((4, 5, 1)))
    assert read_image(tmp_path / "one.npy").shape == (4, 5)


def test_nan_refused_naming_file(tmp_path):
    a = np.zeros((4, 5))
    a[1, 2] = np.nan
    a[0, 0] = np.inf
    np.save(tmp_path / "bad.npy", a)
    with pytest.raises(ImageError, match=r"bad\.npy.*2 pixel\(s\) are NaN or Inf"):
        read_image(tmp_path / "bad.npy")


def test_wrong_size_names_both_shapes_and_file(tmp_path, img):
    p = write_image(tmp_path / "small.png", img)
    with pytest.raises(ImageError, match=r"small\.png.*\(7, 9\).*\(8, 9\)"):
        read_image(p, shape=(8, 9))
    with pytest.raises(ImageError, match=r"small\.png.*\(7, 9\)"):
        ImageSource(p, shape=(8, 9)).read_all()


def test_unknown_and_missing(tmp_path):
    with pytest.raises(ImageError, match="unknown image format"):
        read_image(tmp_path / "x.jpg")
    with pytest.raises(ImageError, match="no such file"):
        ImageSource(tmp_path / "missing.png")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ImageError, match="no image files"):
        ImageSource(tmp_path / "empty")
    with pytest.raises(ImageError, match="pixel type"):
        check_image(np.zeros((2, 2), np.complex64))


def test_compensate_writes_nothing_for_a_folder_with_one_colour_frame(tmp_path, capsys):
    """A grey X and a folder whose last frame is colour: refused, naming the frame, from
    the frames' headers before the first projector image is written."""
    from bigT.cli import main

    H, W = 6, 8
    _, X, _, _ = random_transport(H, W, seed=5)
    make_store(X, tmp_path / "X.zarr", image_shape=(H, W), tile_size=16)
    for i in range(3):
        write_image(tmp_path / "in" / f"f{i}.png", np.full((H, W), 0.3))
    write_image(tmp_path / "in" / "f9.png", np.full((H, W, 3), 0.3))
    assert main(["compensate", str(tmp_path / "X.zarr"), str(tmp_path / "in"), "-o",
                 str(tmp_path / "out"), "--batch", "1", "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "f9.png: colour image (6, 8, 3)" in err, err
    assert not (tmp_path / "out").exists()
