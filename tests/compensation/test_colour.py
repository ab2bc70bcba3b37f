"""Colour compensation (issue 28, points 5 and 6): RGB images, folders and video through
`bigT compensate`, `relight` and `--simulate`, against dense numpy references (the
row-major 3n x 3n matrices the stores were written from, index 3 (y W + x) + c); the
encoding, per-channel clipping and the metrics; grey given to colour and the reverse
refused in one line with nothing written."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT import colour
from bigT.cli import main
from bigT.compensation import compensate, compensate_files, relight_files, simulate
from bigT.compensation.encoding import FrameEncoding
from bigT.compensation.video import VideoSink, VideoSource
from bigT.images import read_image, write_image
from bigT.metrics import image_metrics

from comp_helpers import make_store

H, W = 6, 8
N = 3 * H * W


def _colour_transport(seed=0):
    """A colour transport T = (I - A)^-1 F (A: interreflection between any two values,
    F: a 3x3 colour-mixing block per pixel with cross-talk), dense row-major, and its
    exact inverse X."""
    rng = np.random.default_rng(seed)
    A = sp.random(N, N, density=0.05, random_state=rng).toarray()
    np.fill_diagonal(A, 0.0)
    A *= 0.35 / np.maximum(A.sum(axis=1, keepdims=True), 1e-12)
    F = np.zeros((N, N))
    for p in range(H * W):
        block = np.diag(rng.uniform(0.6, 1.0, 3)) + rng.uniform(0.0, 0.08, (3, 3))
        F[3 * p:3 * p + 3, 3 * p:3 * p + 3] = block
    T = np.linalg.solve(np.eye(N) - A, F)
    return T, np.linalg.inv(T)


def _store(M, path, channels=3, shape=(H, W)):
    return bigT.from_scipy(sp.csr_array(M), path, tile_size=48, image_shape=shape,
                           pixel_order="tile-major", image_tile=(2, 4), channels=channels,
                           dtype="float32")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("colour")
    T, X = _colour_transport()
    _store(T, d / "T.zarr")
    _store(X, d / "X.zarr")
    grey = np.linalg.inv(np.eye(H * W) + 0.05)  # a grey inverse of the same image size
    make_store(grey, d / "G.zarr", image_shape=(H, W), tile_size=16)
    return d, T, X


def _desired(k, seed=1):
    return np.random.default_rng(seed).uniform(0.1, 0.9, (k, H, W, 3))


def _apply(M, frames):
    """M @ each frame's row-major vector: (K, H, W, 3) -> (K, H, W, 3)."""
    return np.einsum("ij,kj->ki", M, frames.reshape(len(frames), -1)).reshape(frames.shape)


def _levels(values):
    return np.rint(np.clip(values, 0, 1) * 255)


def _run(argv, capsys):
    rc = main(argv)
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def test_8bit_colour_png_is_decoded_from_srgb_and_encoded_back(scene, tmp_path):
    d, _, X = scene
    desired = _levels(_desired(1)[0]) / 255  # exactly what the 8-bit file holds
    write_image(tmp_path / "in.png", desired, bits=8)
    report = compensate_files(d / "X.zarr", tmp_path / "in.png", tmp_path / "out.png")
    assert report.encoding.name == "srgb" and "8-bit colour" in report.encoding.reason

    projector = _apply(X, colour.decode(desired, "srgb")[None])[0]  # linear light
    expected = _levels(colour.encode(np.clip(projector, 0, 1), "srgb"))
    got = read_image(tmp_path / "out.png", (H, W), channels=3) * 255
    assert got.shape == (H, W, 3)
    assert np.abs(got - expected).max() <= 1  # float32 X: at most one level off
    assert np.mean(got == expected) > 0.97
    c = report.compensation
    low = [(projector[..., k] < 0).sum() for k in range(3)]
    high = [(projector[..., k] > 1).sum() for k in range(3)]
    assert c.clipped_low_by_channel == tuple(low) and c.clipped_high_by_channel == tuple(high)
    assert (c.clipped_low, c.clipped_high, c.pixels) == (sum(low), sum(high), 3 * H * W)
    assert "srgb-encoded, as the input" in report.describe()
    assert "per channel below / above: R" in report.describe()


@pytest.mark.parametrize("resident", [True, False])
def test_folder_of_float_frames_is_linear_in_memory_and_streamed(scene, tmp_path, resident):
    d, _, X = scene
    frames = _desired(5, seed=2)
    for i, f in enumerate(frames):
        np.save(tmp_path / f"f{i}.npy", f)
    (tmp_path / "in").mkdir()
    for i in range(5):
        (tmp_path / f"f{i}.npy").rename(tmp_path / "in" / f"f{i}.npy")
    report = compensate_files(d / "X.zarr", tmp_path / "in", tmp_path / "out", clip=None,
                              batch=2, resident=resident)
    assert report.residency.resident == resident and report.encoding.name == "linear"
    want = _apply(X, frames)
    for i in range(5):
        np.testing.assert_allclose(np.load(tmp_path / "out" / f"f{i}.npy"), want[i],
                                   rtol=1e-5, atol=1e-5)


def test_clipping_per_channel_of_the_array_api_matches_numpy(scene):
    d, _, X = scene
    frames = np.random.default_rng(3).uniform(0.0, 1.0, (4, H, W, 3))
    frames[..., 0] *= 1.6  # red asks for more than the projector has
    out, report = compensate(d / "X.zarr", frames, clip=(0, 1), batch=3, return_report=True)
    raw = _apply(X, frames)
    np.testing.assert_allclose(out, np.clip(raw, 0, 1), atol=2e-5)
    low = tuple(int((raw[..., c] < 0).sum()) for c in range(3))
    high = tuple(int((raw[..., c] > 1).sum()) for c in range(3))
    assert report.clipped_low_by_channel == low and report.clipped_high_by_channel == high
    assert high[0] > high[1] and high[0] > high[2]
    per = raw[..., 0].size
    assert report.clipped_shares_by_channel == tuple((lo / per, hi / per)
                                                     for lo, hi in zip(low, high))


def test_colour_video_through_the_cli_matches_dense_numpy(scene, tmp_path, capsys):
    d, _, X = scene
    frames = _levels(_desired(7, seed=4)) / 255
    with VideoSink(tmp_path / "in.mkv", (H, W), 25, 8, channels=3) as sink:
        sink.write(frames)
    for batch in ("1", "3"):
        out = tmp_path / f"out{batch}.mkv"
        rc, text, _ = _run(["compensate", str(d / "X.zarr"), str(tmp_path / "in.mkv"),
                            "-o", str(out), "--batch", batch, "--no-progress"], capsys)
        assert rc == 0, text
        assert "encoding srgb (8-bit colour video)" in text
        got = np.stack(list(VideoSource(out, channels=3).frames())) * 255.0
        projector = np.clip(_apply(X, colour.decode(frames, "srgb")), 0, 1)
        expected = _levels(colour.encode(projector, "srgb"))
        assert got.shape == (7, H, W, 3)
        assert np.abs(got - expected).max() <= 1


def test_encoding_linear_is_taken_at_its_word(scene, tmp_path, capsys):
    d, _, X = scene
    desired = _levels(_desired(1, seed=5)[0]) / 255
    write_image(tmp_path / "in.png", desired, bits=8)
    rc, text, _ = _run(["compensate", str(d / "X.zarr"), str(tmp_path / "in.png"), "-o",
                        str(tmp_path / "out.png"), "--encoding", "linear", "--json",
                        "--no-progress"], capsys)
    assert rc == 0
    report = json.loads(text)  # --json: one object, nothing else on stdout
    assert report["encoding"] == "linear" and report["encoding_reason"] == "asked for"
    raw = _apply(X, desired[None])[0]
    assert report["clipped_by_channel"]["G"]["below"] == int((raw[..., 1] < 0).sum())
    assert report["clipped_by_channel"]["B"]["above"] == int((raw[..., 2] > 1).sum())
    got = read_image(tmp_path / "out.png", channels=3) * 255
    assert np.abs(got - _levels(raw)).max() <= 1


@pytest.mark.parametrize("store, image, words", [
    ("X.zarr", "grey.png", r"grey.png: grey image \(6, 8\) given to a colour transport"),
    ("G.zarr", "rgb.png", r"rgb.png: colour image \(6, 8, 3\) .* given to a grey transport"),
    ("X.zarr", "greys", r"b.png: grey image \(6, 8\) given to a colour transport"),
    ("X.zarr", "grey.mkv", r"grey video .* given to a colour transport"),
    ("G.zarr", "rgb.mkv", r"colour video .* grey transport"),
])
def test_grey_for_colour_and_the_reverse_are_one_line_exit_2(scene, tmp_path, capsys, store,
                                                             image, words):
    d, _, _ = scene
    write_image(tmp_path / "grey.png", np.full((H, W), 0.5), bits=8)
    write_image(tmp_path / "rgb.png", _desired(1)[0], bits=8)
    write_image(tmp_path / "greys" / "a.png", np.full((H, W, 3), 0.5), bits=8)
    write_image(tmp_path / "greys" / "b.png", np.full((H, W), 0.5), bits=8)
    with VideoSink(tmp_path / "grey.mkv", (H, W), 25, 8) as sink:
        sink.write(np.full((2, H, W), 0.5))
    with VideoSink(tmp_path / "rgb.mkv", (H, W), 25, 8, channels=3) as sink:
        sink.write(_desired(2))
    out = tmp_path / ("out.mkv" if image.endswith(".mkv") else
                      "out" if "." not in image else "out.png")
    rc, text, err = _run(["compensate", str(d / store), str(tmp_path / image), "-o", str(out),
                          "--no-progress"], capsys)
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and re.search(words, err)
    assert not out.exists()


def test_relight_of_a_colour_image(scene, tmp_path):
    d, T, _ = scene
    projector = _levels(_desired(1, seed=6)[0]) / 255
    write_image(tmp_path / "p.png", projector, bits=8)
    report = relight_files(d / "T.zarr", tmp_path / "p.png", tmp_path / "seen.tif")
    assert report.encoding.name == "srgb"
    seen = _apply(T, colour.decode(projector, "srgb")[None])[0]
    np.testing.assert_allclose(read_image(tmp_path / "seen.tif", channels=3),
                               colour.encode(seen, "srgb"), rtol=1e-5, atol=1e-5)


def test_simulation_metrics_are_bigT_metrics_of_the_same_images(scene):
    d, T, X = scene
    desired = _desired(2, seed=7)
    sim = simulate(d / "X.zarr", desired, d / "T.zarr", metrics="srgb", clip=None)
    r = sim.report
    per_frame = [image_metrics(colour.encode(s, "srgb"), colour.encode(t, "srgb"),
                               encoding_for_lab="srgb") for s, t in zip(sim.seen, desired)]
    for field in ("psnr_db", "ssim", "delta_e_mean", "delta_e_p95", "relative_error"):
        assert getattr(r.metrics, field) == pytest.approx(
            np.mean([getattr(m, field) for m in per_frame]), rel=1e-12)
    uncompensated = _apply(T, desired)
    want0 = [image_metrics(colour.encode(s, "srgb"), colour.encode(t, "srgb"),
                           encoding_for_lab="srgb") for s, t in zip(uncompensated, desired)]
    assert r.metrics_uncompensated.delta_e_mean == pytest.approx(
        np.mean([m.delta_e_mean for m in want0]), rel=1e-4)
    assert r.metrics_uncompensated.psnr_db == pytest.approx(
        np.mean([m.psnr_db for m in want0]), rel=1e-4)
    # the exact inverse, unclipped: compensation all but removes the error
    assert r.metrics.delta_e_mean < 0.01 < r.metrics_uncompensated.delta_e_mean
    np.testing.assert_allclose(sim.seen, desired, atol=1e-4)
    assert "ΔE2000 mean" in r.describe() and "compensated:" in r.describe()


def test_simulate_cli_json_carries_the_metrics(scene, tmp_path, capsys):
    d, _, _ = scene
    write_image(tmp_path / "in.png", _desired(1, seed=8)[0], bits=8)
    rc, text, _ = _run(["compensate", str(d / "X.zarr"), str(tmp_path / "in.png"), "-o",
                        str(tmp_path / "out.png"), "--simulate", str(d / "T.zarr"), "--json",
                        "--no-progress"], capsys)
    assert rc == 0
    report = json.loads(text)
    assert report["encoding"] == "srgb"
    for key in ("metrics", "metrics_uncompensated"):
        assert set(report[key]) == {"relative_error", "psnr_db", "ssim", "delta_e_mean",
                                    "delta_e_p95"}
    assert report["metrics"]["delta_e_mean"] < report["metrics_uncompensated"]["delta_e_mean"]
    assert set(report["clipped_by_channel"]) == {"R", "G", "B"}
    assert read_image(tmp_path / "out_seen.png", channels=3).shape == (H, W, 3)


def test_grey_simulation_reports_metrics_of_the_grey_images(tmp_path, small_scene):
    s = small_scene
    make_store(s["X"], tmp_path / "X.zarr", image_shape=(s["H"], s["W"]))
    make_store(s["T"], tmp_path / "T.zarr", image_shape=(s["H"], s["W"]))
    desired = np.random.default_rng(9).uniform(0.2, 0.8, (s["H"], s["W"]))
    sim = simulate(tmp_path / "X.zarr", desired, tmp_path / "T.zarr")
    want = image_metrics(sim.seen, desired)
    assert sim.report.metrics == want and sim.report.encoding == "linear"
    assert sim.report.clipped_low_by_channel == (sim.report.clipped_low,)


def test_matrix_free_colour_is_the_series_with_3x3_blocks(scene):
    """The matrix-free path applies F^-1 sum_k M^k with F the 3x3 diagonal blocks of T:
    against the same series in dense numpy."""
    d, T, _ = scene
    desired = _desired(1)[0]
    F = np.zeros_like(T)
    for p in range(H * W):
        F[3 * p:3 * p + 3, 3 * p:3 * p + 3] = T[3 * p:3 * p + 3, 3 * p:3 * p + 3]
    Finv = np.linalg.inv(F)
    M = np.eye(N) - T @ Finv
    b = desired.ravel()
    s = b.copy()
    for _ in range(3):
        s = b + M @ s
    want = np.clip(Finv @ s, 0, 1).reshape(H, W, 3)
    got = compensate(None, desired, T=d / "T.zarr", path="matrix-free", terms=3)
    np.testing.assert_allclose(got, want, atol=2e-5)


def test_colour_bounces_sum_to_the_seen_image_and_match_dense(scene, tmp_path, capsys):
    """Bounce k = A^k F l with F the inverse of X's 3x3 diagonal blocks and A = I - F X
    (dense numpy), the parts summing to T l; the CLI writes RGB parts."""
    from bigT.compensation import separate_bounces

    d, T, X = scene
    light = _desired(1)[0]
    T32 = T.astype(np.float32).astype(np.float64)
    X32 = X.astype(np.float32).astype(np.float64)
    F = np.zeros_like(X32)
    for p in range(H * W):
        F[3 * p:3 * p + 3, 3 * p:3 * p + 3] = np.linalg.inv(X32[3 * p:3 * p + 3, 3 * p:3 * p + 3])
    A = np.eye(N) - F @ X32
    v = F @ light.ravel()
    want = [v]
    for _ in range(2):
        v = A @ v
        want.append(v)
    parts = separate_bounces(d / "T.zarr", d / "X.zarr", light, 2)
    assert parts.shape == (4, H, W, 3)
    for got, ref in zip(parts[:3], want):
        np.testing.assert_allclose(got.ravel(), ref, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(parts.sum(axis=0).ravel(), T32 @ light.ravel(), rtol=1e-6,
                               atol=1e-9)
    write_image(tmp_path / "l.tif", light.astype(np.float32))
    rc, out, err = _run(["bounces", str(d / "T.zarr"), str(d / "X.zarr"),
                         str(tmp_path / "l.tif"), "-o", str(tmp_path / "parts"),
                         "--bounces", "2"], capsys)
    assert rc == 0, err
    assert read_image(tmp_path / "parts" / "bounce_0.tif", channels=3).shape == (H, W, 3)
    assert (tmp_path / "parts" / "bounces.png").exists()


def test_srgb_kernel_matches_bigT_colour():
    rng = np.random.default_rng(10)
    values = rng.uniform(-0.2, 1.3, (3, 100, 300, 3)).astype(np.float32)  # > the kernel floor
    e = FrameEncoding("srgb", "test")
    light = e.to_light(values)
    assert light.dtype == np.float32
    np.testing.assert_allclose(light, colour.decode(values, "srgb"), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(e.from_light(values), colour.encode(values, "srgb"),
                               rtol=1e-6, atol=1e-7)


def test_large_batches_count_clipped_values_per_channel_as_numpy():
    from bigT.compensation.core import clipped_by_channel

    Y = np.random.default_rng(11).normal(0.5, 0.5, (3 * 40_000, 9)).astype(np.float32)
    assert Y.size > 1 << 18  # the kernel's side of the threshold
    Y3 = Y.reshape(-1, 3, 9)
    for clip in [(0, 1), (0.2, None), (None, 0.7)]:
        low, high = clipped_by_channel(Y, clip, 3)
        want_low = [0 if clip[0] is None else int((Y3[:, c] < clip[0]).sum()) for c in range(3)]
        want_high = [0 if clip[1] is None else int((Y3[:, c] > clip[1]).sum()) for c in range(3)]
        assert list(low) == want_low and list(high) == want_high


def test_colour_video_codes_path_is_the_float_path_and_numpy(scene, tmp_path):
    """A 16-bit colour video (linear light by default) with X in memory takes the codes
    path (FileCompensation.takes_codes): its codes are the float path's bit for bit, and
    within half a code (float32 sums) of the dense float64 product, per channel."""
    from bigT.compensation.files import FileCompensation

    d, _, X = scene
    rng = np.random.default_rng(4)
    frames = rng.uniform(0.1, 0.7, (5, H, W, 3))
    with VideoSink(tmp_path / "in.mkv", (H, W), 25, 16, channels=3) as sink:
        sink.write(frames)
    with FileCompensation(d / "X.zarr", tmp_path / "in.mkv", tmp_path / "out.mkv",
                          batch=2) as job:
        assert job.takes_codes and job.encoding.linear
        job.run()
    got = np.stack(list(VideoSource(tmp_path / "out.mkv", channels=3).codes())).astype(float)
    light = np.stack(list(VideoSource(tmp_path / "in.mkv", channels=3).frames()))
    with FileCompensation(d / "X.zarr", tmp_path / "in.mkv", tmp_path / "f.mkv") as floats:
        want = np.rint(np.clip(floats.compensator(light), 0, 1) * np.float32(65535))
    np.testing.assert_array_equal(got, want)
    ref = _apply(X, light.astype(np.float64))  # the row-major dense inverse
    sums = _apply(np.abs(X), light.astype(np.float64)).max()
    assert np.abs(got - np.clip(ref, 0, 1) * 65535).max() <= 0.5 + N * 2.0 ** -24 * sums * 65535
