"""bigT compensate of videos and folders of frames (bigT.compensation.realtime/video):
X in memory equals X streamed and the dense product; lossless video round trips; bad
inputs are one line naming the file with nothing written."""

from __future__ import annotations

import numpy as np
import pytest

from bigT.cli import main
from bigT.compensation.realtime import run_stream
from bigT.compensation.video import VideoSink, VideoSource
from bigT.errors import ImageError
from bigT.images import read_image, write_image

from comp_helpers import make_store, random_transport

H, W = 12, 16
K = 7  # frames: batches of 3 leave a short last one


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """X (tile-major, 3 tile rows) of a dense random transport, its row-major dense
    copy, and K smooth moving frames in [0.15, 0.55]."""
    d = tmp_path_factory.mktemp("video")
    _, X, _, _ = random_transport(H, W, seed=5)
    make_store(X, d / "X.zarr", image_shape=(H, W), tile_size=64, pixel_order="tile-major")
    t = np.arange(K)[:, None, None]
    y, x = np.mgrid[0:H, 0:W]
    frames = 0.35 + 0.2 * np.sin(0.5 * x + 0.3 * y + 0.7 * t)
    return d, X, frames


def _expected(X, frames, clip=True):
    out = np.einsum("ij,kj->ki", X, frames.reshape(len(frames), -1)).reshape(frames.shape)
    return np.clip(out, 0, 1) if clip else out


def _write_video(path, frames, bits=8):
    with VideoSink(path, frames.shape[1:], 25, bits) as sink:
        sink.write(frames)
    top = 65535 if bits == 16 else 255
    return np.rint(np.clip(frames, 0, 1) * top) / top  # what the video holds


def _read_video(path):
    return np.stack(list(VideoSource(path).frames())).astype(np.float64)


def _run(argv, capsys):
    rc = main(argv)
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def test_in_memory_equals_streamed_and_dense(scene, tmp_path, capsys):
    d, X, frames = scene
    for i, f in enumerate(frames):
        write_image(tmp_path / "in" / f"f{i}.npy", f)
    base = ["compensate", str(d / "X.zarr"), str(tmp_path / "in"), "--clip", "none",
            "--no-progress", "--batch", "3"]
    rc, out, err = _run(base + ["-o", str(tmp_path / "mem")], capsys)
    assert rc == 0
    assert "X held in memory" in err and "bytes) of X read per frame" in err
    assert "latency per frame mean" in out and "X in memory" in out
    rc, out, err = _run(base + ["-o", str(tmp_path / "disk"), "--stream"], capsys)
    assert rc == 0 and "X streamed from disk" in err and "X streamed" in out
    rc, _, err = _run(base + ["-o", str(tmp_path / "small"), "--memory-limit", "1KiB"], capsys)
    assert rc == 0 and "over the memory limit of 0 MiB" in err  # streamed: does not fit
    want = _expected(X, frames, clip=False)
    for i in range(K):
        mem = read_image(tmp_path / "mem" / f"f{i}.npy")
        disk = read_image(tmp_path / "disk" / f"f{i}.npy")
        np.testing.assert_allclose(mem, disk, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(mem, want[i], rtol=1e-5, atol=1e-6)
        np.testing.assert_array_equal(read_image(tmp_path / "small" / f"f{i}.npy"), disk)


@pytest.mark.parametrize("suffix, bits", [(".mkv", 8), (".mp4", 8), (".avi", 16)])
def test_video_round_trip_is_lossless(scene, tmp_path, capsys, suffix, bits):
    """FFV1 and H.264 at qp 0 keep every level: the output is clip(X l) rounded to the
    video's levels, to half a level (plus float32 rounding)."""
    d, X, frames = scene
    held = _write_video(tmp_path / f"in{suffix}", frames, bits)
    out = tmp_path / f"out{suffix}"
    rc, text, err = _run(["compensate", str(d / "X.zarr"), str(tmp_path / f"in{suffix}"),
                          "-o", str(out), "--batch", "3", "--no-progress"], capsys)
    assert rc == 0, err
    assert f"{K} frame(s) in" in text and f"wrote projector input -> {out}" in text
    got = _read_video(out)
    top = 65535 if bits == 16 else 255
    assert got.shape == (K, H, W)
    assert np.abs(got - _expected(X, held)).max() <= 0.5 / top + 1e-5
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no litter


def test_serial_batch_one_and_float16_agree(scene, tmp_path, capsys):
    d, X, frames = scene
    _write_video(tmp_path / "in.mkv", frames, 16)
    outs = {}
    for name, extra in (("overlap", []), ("serial", ["--serial"]),
                        ("f16", ["--precision", "float16"])):
        out = tmp_path / f"{name}.mkv"
        rc, text, _ = _run(["compensate", str(d / "X.zarr"), str(tmp_path / "in.mkv"), "-o",
                            str(out), "--batch", "1", "--bits", "16", "--no-progress", *extra],
                           capsys)
        assert rc == 0
        assert ("one batch at a time" in text) == (name == "serial")
        outs[name] = _read_video(out)
    np.testing.assert_array_equal(outs["overlap"], outs["serial"])
    # binary16 values: 2^-11 of sum |X_ij| l_j, here < 1.6 levels of 65535
    bound = 2.0 ** -11 * (np.abs(X) @ np.ones(H * W)).max() + 1.0 / 65535
    assert np.abs(outs["f16"] - outs["overlap"]).max() <= bound


def test_folder_to_video(scene, tmp_path, capsys):
    d, X, frames = scene
    for i, f in enumerate(frames):
        write_image(tmp_path / "in" / f"f{i:02d}.png", f, bits=16)
    rc, _, err = _run(["compensate", str(d / "X.zarr"), str(tmp_path / "in"), "-o",
                       str(tmp_path / "out.mkv"), "--bits", "16", "--fps", "50",
                       "--no-progress"], capsys)
    assert rc == 0, err
    assert VideoSource(tmp_path / "out.mkv").info.fps == 50
    held = np.stack([read_image(tmp_path / "in" / f"f{i:02d}.png") for i in range(K)])
    got = _read_video(tmp_path / "out.mkv")
    assert np.abs(got - _expected(X, held)).max() <= 0.5 / 65535 + 1e-5


def _refused(argv, capsys, name):
    rc, _, err = _run(argv, capsys)
    lines = err.strip().splitlines()
    assert rc == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert name in lines[0], lines[0]
    return lines[0]


def test_bad_videos_are_one_line_and_write_nothing(scene, tmp_path, capsys):
    d, X, frames = scene
    x = str(d / "X.zarr")
    out = tmp_path / "out.mp4"
    _write_video(tmp_path / "small.mkv", np.full((3, H - 2, W), 0.5))
    line = _refused(["compensate", x, str(tmp_path / "small.mkv"), "-o", str(out)], capsys,
                    "small.mkv")
    assert "(10, 16) do not match the transport's image shape (12, 16)" in line
    (tmp_path / "garbage.mp4").write_bytes(b"not a video at all" * 100)
    line = _refused(["compensate", x, str(tmp_path / "garbage.mp4"), "-o", str(out)], capsys,
                    "garbage.mp4")
    assert "cannot read the video" in line
    _refused(["compensate", x, str(tmp_path / "none.mp4"), "-o", str(out)], capsys, "none.mp4")
    _write_video(tmp_path / "ok.mkv", frames)
    line = _refused(["compensate", x, str(tmp_path / "ok.mkv"), "-o", str(tmp_path / "o.png")],
                    capsys, "o.png")
    assert "output must be one too" in line
    _refused(["compensate", x, str(tmp_path / "ok.mkv"), "-o", str(tmp_path / "o.mp4"),
              "--bits", "16"], capsys, "o.mp4")
    _refused(["compensate", x, str(tmp_path / "ok.mkv"), "-o", str(out), "--simulate", x],
             capsys, "ok.mkv")
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(("out", "o.", "."))]


def test_colour_video_refused(scene, tmp_path, capsys):
    import imageio_ffmpeg

    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[..., 0] = 200  # red
    gen = imageio_ffmpeg.write_frames(str(tmp_path / "red.mkv"), (W, H), codec="ffv1",
                                      pix_fmt_in="rgb24", pix_fmt_out="bgr0",
                                      macro_block_size=1, ffmpeg_log_level="error")
    gen.send(None)
    gen.send(rgb.tobytes())
    gen.close()
    line = _refused(["compensate", str(scene[0] / "X.zarr"), str(tmp_path / "red.mkv"), "-o",
                     str(tmp_path / "out.mkv")], capsys, "red.mkv")
    assert "colour video" in line and "given to a grey transport (1 channel)" in line
    assert not (tmp_path / "out.mkv").exists()


def test_folder_with_one_bad_frame_writes_nothing(scene, tmp_path, capsys):
    d, X, frames = scene
    for i, f in enumerate(frames):
        write_image(tmp_path / "in" / f"f{i}.png", f)
    write_image(tmp_path / "in" / "f9.png", np.zeros((H, W + 1)))  # the last one
    line = _refused(["compensate", str(d / "X.zarr"), str(tmp_path / "in"), "-o",
                     str(tmp_path / "out")], capsys, "f9.png")
    assert "does not match" in line
    assert not (tmp_path / "out").exists()


def test_failure_mid_stream_leaves_no_video(tmp_path):
    """An error after some frames were encoded (here the third batch's) discards the
    partial video: the destination keeps its old contents, no hidden file is left."""
    dest = tmp_path / "out.mkv"
    dest.write_bytes(b"old")
    batches = ((i, np.full((1, H, W), 0.5, np.float32)) for i in range(5))

    def compute(frames):
        if compute.calls == 2:
            raise RuntimeError("boom")
        compute.calls += 1
        return frames

    compute.calls = 0
    with pytest.raises(RuntimeError, match="boom"):
        with VideoSink(dest, (H, W), 30) as sink:
            run_stream(batches, compute, lambda names, out: sink.write(out), batch=1)
    assert dest.read_bytes() == b"old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mkv"]


@pytest.mark.parametrize("overlap", [True, False])
def test_stream_report_counts_every_frame(overlap):
    written = []
    batches = (([i, i + 1], np.full((2, 2, 2), float(i))) for i in range(0, 6, 2))
    rep = run_stream(batches, lambda f: f * 2, lambda n, f: written.extend(n), batch=2,
                     overlap=overlap)
    assert written == list(range(6)) and rep.frames == 6 and rep.latencies.shape == (6,)
    lat = rep.latency_ms()
    assert 0 <= lat["p50"] <= lat["p95"] <= lat["max"] and rep.frames_per_second > 0
    assert "6 frame(s)" in rep.summary()
    assert rep.service.shape == (6,) and np.all(rep.service <= rep.latencies)


@pytest.mark.parametrize("clip", [(0, 1), None])
def test_pixel_reordering_on_threads_matches_one_thread(clip):
    from bigT.storage.frames import frames_to_matrix, matrix_to_frames
    from bigT.storage.pixel_order import PixelOrder

    order = PixelOrder((96, 128), "tile-major")
    frames = np.random.default_rng(0).uniform(-0.2, 1.2, (3, 96, 128))
    one = frames_to_matrix(frames, order, np.float32)
    two = frames_to_matrix(frames, order, np.float32, n_threads=2)
    np.testing.assert_array_equal(one, two)
    np.testing.assert_array_equal(one, order.to_matrix(frames).reshape(order.n, 3).astype(np.float32))
    back1 = matrix_to_frames(one, order, clip)
    back2 = matrix_to_frames(one, order, clip, dtype=np.float32, n_threads=2)
    np.testing.assert_array_equal(back1[0].astype(np.float32), back2[0])
    assert back1[1:] == back2[1:] and (clip is None) == (back1[1] + back1[2] == 0)


# --- colour (issue #28) ---------------------------------------------------------------

def _levels(shape, bits, seed=0):
    """Frames of exact levels k / top, so a lossless round trip is an equality."""
    top = 2 ** bits - 1
    return np.random.default_rng(seed).integers(0, top + 1, shape) / top


@pytest.mark.parametrize("suffix, bits", [(".mkv", 8), (".mkv", 16), (".avi", 16),
                                          (".mp4", 8), (".mov", 8)])
def test_colour_video_round_trip_is_exact(tmp_path, suffix, bits):
    """FFV1 (bgr0 / rgb48le) and libx264rgb at qp 0 give back every level of every
    channel; a colour source reads (H, W, 3) frames as RGB in order."""
    frames = _levels((K, H, W, 3), bits)
    path = tmp_path / f"c{suffix}"
    with VideoSink(path, (H, W), 25, bits, channels=3) as sink:
        sink.write(frames[:3])
        sink.write(frames[3])  # one (H, W, 3) frame
        sink.write(frames[4:])
    source = VideoSource(path, (H, W), channels=3)
    assert source.info.channels == 3 and source.info.bits == bits
    assert source.frame_shape == (H, W, 3)
    got = np.stack(list(source.frames()))
    assert got.shape == (K, H, W, 3) and got.dtype == np.float32
    top = 2 ** bits - 1
    np.testing.assert_array_equal(np.rint(got.astype(np.float64) * top),
                                  np.rint(frames * top))


def test_grey_video_to_a_colour_transport_refused_in_one_line(tmp_path):
    _write_video(tmp_path / "grey.mkv", np.full((2, H, W), 0.5))
    with pytest.raises(ImageError) as e:
        VideoSource(tmp_path / "grey.mkv", (H, W), channels=3)
    line = str(e.value)
    assert "\n" not in line and "grey.mkv: grey video (pixel format gray) given to a colour " \
        "transport (3 channels): give a colour video, or use a grey transport" in line


def test_colour_video_to_a_grey_transport_refused_in_one_line(tmp_path):
    frames = np.zeros((2, H, W, 3))
    frames[..., 0] = 0.8  # red
    with VideoSink(tmp_path / "red.mp4", (H, W), 25, channels=3) as sink:
        sink.write(frames)
    with pytest.raises(ImageError) as e:
        VideoSource(tmp_path / "red.mp4", (H, W))
    line = str(e.value)
    assert "\n" not in line and "red.mp4: colour video (channels of the first frame differ " \
        "by up to 204 levels) given to a grey transport (1 channel)" in line


def test_colour_stream_of_grey_pictures_is_either(tmp_path):
    """An RGB stream whose pictures are neutral is read by a grey transport (as before
    colour) and by a colour one (colour that happens to be grey): the same levels."""
    grey = _levels((2, H, W), 8, seed=4)
    with VideoSink(tmp_path / "n.mkv", (H, W), 25, channels=3) as sink:
        sink.write(np.repeat(grey[..., None], 3, axis=-1))
    as_grey = np.stack(list(VideoSource(tmp_path / "n.mkv", (H, W)).frames()))
    as_colour = np.stack(list(VideoSource(tmp_path / "n.mkv", (H, W), channels=3).frames()))
    np.testing.assert_array_equal(np.rint(as_grey * 255.0), np.rint(grey * 255))
    for c in range(3):
        np.testing.assert_array_equal(as_colour[..., c], as_grey)


def test_channels_other_than_1_or_3_refused(tmp_path):
    _write_video(tmp_path / "g.mkv", np.full((1, H, W), 0.5))
    with pytest.raises(ImageError, match="1 \\(grey\\) or 3 \\(RGB\\) channels, not 4"):
        VideoSource(tmp_path / "g.mkv", channels=4)
    with pytest.raises(ImageError, match="1 \\(grey\\) or 3 \\(RGB\\) channels, not 2"):
        VideoSink(tmp_path / "o.mkv", (H, W), 25, channels=2)


@pytest.mark.parametrize("bits, suffix", [(8, ".mp4"), (16, ".mkv")])
@pytest.mark.parametrize("clip", [(0, 1), (0.2, 0.5), (0, None)])
def test_codes_path_equals_the_float_path_and_scipy(scene, tmp_path, bits, suffix, clip):
    """A linear video with X in memory goes through the products as integer codes
    (FileCompensation.takes_codes): the codes written are those of the float path
    (Compensator on frames of light, quantised as VideoSink.write does), bit for bit,
    and within half a code (float32 sums) of scipy's float64 product; the clip counts
    agree."""
    import scipy.sparse as sp

    from bigT.compensation.files import FileCompensation

    d, X, frames = scene
    _write_video(tmp_path / f"in{suffix}", frames, bits)
    job = FileCompensation(d / "X.zarr", tmp_path / f"in{suffix}", tmp_path / f"out{suffix}",
                           batch=3, clip=clip)
    with job:
        assert job.takes_codes
        report = job.run()
    top = 65535 if bits == 16 else 255
    got = np.rint(_read_video(tmp_path / f"out{suffix}") * top)
    light = np.stack(list(VideoSource(tmp_path / f"in{suffix}").frames()))
    with FileCompensation(d / "X.zarr", tmp_path / f"in{suffix}", tmp_path / f"f{suffix}",
                          clip=clip) as floats:
        projected = floats.compensator(light)
        counts = floats.compensator.report
    want = np.rint(np.clip(projected, 0, 1) * np.float32(top))
    np.testing.assert_array_equal(got, want)
    assert (report.compensation.clipped_low, report.compensation.clipped_high) == (
        counts.clipped_low, counts.clipped_high)
    # X is tile-major, _expected's dense X row-major: scipy against it, in float64
    ref = sp.csr_array(X) @ light.reshape(K, -1).T.astype(np.float64)
    lo, hi = clip
    ref = np.clip(ref.T.reshape(light.shape), lo, hi if hi is not None else np.inf)
    # half a code of rounding, and float32 sums of H W terms (n u sum |X_ij| l_j)
    sums = (np.abs(X) @ light.reshape(K, -1).T.astype(np.float64)).max()
    assert np.abs(got - np.clip(ref, 0, 1) * top).max() <= 0.5 + H * W * 2.0 ** -24 * sums * top
    assert report.compensation.clipped_low + report.compensation.clipped_high > 0 or clip == (0, None)


def test_codes_path_not_taken_for_srgb_or_streamed(scene, tmp_path):
    """sRGB frames (a curve between codes and light) and X streamed from disk keep the
    float path."""
    from bigT.compensation.files import FileCompensation

    d, _, frames = scene
    _write_video(tmp_path / "in.mkv", frames)
    with FileCompensation(d / "X.zarr", tmp_path / "in.mkv", tmp_path / "a.mkv",
                          encoding="srgb") as job:
        assert not job.takes_codes
    with FileCompensation(d / "X.zarr", tmp_path / "in.mkv", tmp_path / "b.mkv",
                          resident=False) as job:
        assert not job.takes_codes
