"""bigT.compensation.pipeline: a folder's frames decoded ahead and encoded behind on a
pool of threads. The output is the sequential path's byte for byte (``overlap=False``
reads, compensates and writes one batch at a time, on one thread), files keep their
names, errors name their frame, and no more than a few frames are ever in flight."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT.compensation import FileCompensation, compensate_files
from bigT.compensation.pipeline import CodecPool, EncodedBehind, decoded_ahead
from bigT.compensation.realtime import image_batches
from bigT.errors import ImageError, OutputError
from bigT.images import ImageSource, read_image, write_image

from comp_helpers import make_store

FRAMES = 9


def _folder(path, shape, frames=FRAMES, seed=3, bits=16):
    """``frames`` random PNG frames (grey for a 2-d shape, RGB for (H, W, 3))."""
    path.mkdir()
    rng = np.random.default_rng(seed)
    for i in range(frames):
        write_image(path / f"frame{i:03d}.png", rng.uniform(0.05, 0.95, shape), bits=bits)
    return path


@pytest.fixture()
def grey(tmp_path, small_scene):
    s = small_scene
    shape = (s["H"], s["W"])
    X = make_store(s["X"], tmp_path / "X.zarr", image_shape=shape, tile_size=32,
                   pixel_order="tile-major")
    return X, _folder(tmp_path / "in", shape), s["X"]


@pytest.fixture()
def colour(tmp_path):
    H, W = 6, 8
    n = 3 * H * W
    rng = np.random.default_rng(5)
    M = np.eye(n) * 0.9 + sp.random(n, n, density=0.05, random_state=rng).toarray() * 0.05
    X = bigT.from_scipy(sp.csr_array(M), tmp_path / "Xc.zarr", tile_size=48, image_shape=(H, W),
                        pixel_order="tile-major", image_tile=(2, 4), channels=3,
                        dtype="float32")
    return X, _folder(tmp_path / "inc", (H, W, 3)), M


def _files(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


@pytest.mark.parametrize("scene", ["grey", "colour"])
@pytest.mark.parametrize("batch", [1, 4])
def test_the_output_is_the_sequential_paths_byte_for_byte(request, tmp_path, scene, batch):
    X, folder, M = request.getfixturevalue(scene)
    with FileCompensation(X, folder, tmp_path / "seq", batch=batch) as job:
        job.run(overlap=False)
    with FileCompensation(X, folder, tmp_path / "pooled", batch=batch) as job:
        report = job.run()
    sequential, pooled = _files(tmp_path / "seq"), _files(tmp_path / "pooled")
    assert list(pooled) == [p.name for p in sorted(folder.iterdir())]  # no hidden file left
    assert pooled == sequential
    # and both are the product, against dense numpy on the decoded input
    for name in list(pooled)[:3]:
        desired = read_image(folder / name)
        expected = np.clip(M @ desired.ravel(), 0, 1).reshape(desired.shape)
        np.testing.assert_allclose(read_image(tmp_path / "pooled" / name), expected,
                                   atol=1.0 / 65535 + 1e-5)
    s = report.stream
    assert s.frames == FRAMES and len(s.latencies) == FRAMES and s.overlap
    # latencies run to each file written: never shorter than its own service time
    assert np.all(s.latencies >= s.service - 1e-9) and s.seconds >= s.latencies.max() - 1e-9


@pytest.mark.parametrize("batch", [1, 2, 4, 20])
def test_decoded_ahead_yields_the_batches_of_the_sequential_reader(grey, batch):
    _, folder, _ = grey
    source = ImageSource(folder)
    with CodecPool(3) as pool:
        pooled = list(decoded_ahead(pool, source, batch, ahead=3))
    sequential = list(image_batches(source, batch))
    assert [f for f, _ in pooled] == [f for f, _ in sequential]
    for (_, a), (_, b) in zip(pooled, sequential):
        assert a.dtype == b.dtype == np.float32 and np.array_equal(a, b)


class _CountingSource:
    """An ImageSource stand-in whose reads take a while and count how many frames have
    been read and not yet consumed."""

    def __init__(self, frames):
        self.files = [f"f{i}" for i in range(frames)]
        self.read_so_far = 0
        self._lock = threading.Lock()

    def read(self, file, dtype=np.float64):
        time.sleep(0.002)
        with self._lock:
            self.read_so_far += 1
        return np.full((2, 3), int(file[1:]), dtype)


def test_decoded_ahead_keeps_at_most_ahead_frames_in_flight():
    source = _CountingSource(40)
    consumed, most = 0, 0
    with CodecPool(4) as pool:
        for files, frames in decoded_ahead(pool, source, 2, ahead=5):
            consumed += len(files)  # yielded
            time.sleep(0.01)  # a slow consumer: the decoders would run far ahead
            most = max(most, source.read_so_far - consumed)
            assert [int(f[1:]) for f in files] == [int(v) for v in frames[:, 0, 0]]
    assert consumed == 40
    assert 2 <= most <= 5


def test_encoded_behind_keeps_at_most_behind_frames_pending_and_keeps_names():
    written, running, most = {}, [0], [0]
    lock = threading.Lock()

    def write(names, frames):
        with lock:
            running[0] += 1
        time.sleep(0.005)
        with lock:
            written[names[0]] = frames[0].copy()
            most[0] = max(most[0], running[0])
            running[0] -= 1

    with CodecPool(4) as pool:
        behind = EncodedBehind(pool, write, behind=3)
        pending_seen = 0
        for start in range(0, 20, 2):
            names = [f"n{start}", f"n{start + 1}"]
            behind.write(names, np.arange(start, start + 2, dtype=float)[:, None])
            pending_seen = max(pending_seen, len(behind._pending))
        times = behind.finish()
    assert pending_seen <= 3 and most[0] <= 3
    assert {k: float(v[0]) for k, v in written.items()} == {f"n{i}": float(i) for i in range(20)}
    assert len(times) == 20 and all(t.done >= t.started > 0 for t in times)


def test_a_damaged_frame_is_named_and_the_frames_written_are_whole(grey, tmp_path):
    X, folder, _ = grey
    bad = folder / "frame004.png"
    data = bad.read_bytes()  # the header intact (the folder's check passes), pixels broken
    bad.write_bytes(data[:60] + bytes(len(data) - 60))
    with FileCompensation(X, folder, tmp_path / "out", batch=1) as job:
        with pytest.raises(ImageError) as err:
            job.run()
    assert "frame004.png" in str(err.value) and "\n" not in str(err.value)
    # complete files only, no hidden sibling; none at all when the error came before
    # the first frame was encoded (frames not started are dropped: a loaded machine)
    out = tmp_path / "out"
    for f in out.iterdir() if out.exists() else ():
        assert not f.name.startswith(".")
        read_image(f)


def test_a_frame_that_cannot_be_written_is_named(grey, tmp_path):
    X, folder, _ = grey
    (tmp_path / "out" / "frame006.png").mkdir(parents=True)  # a folder where a frame goes
    with pytest.raises(OutputError) as err:
        compensate_files(X, folder, tmp_path / "out", batch=1)
    assert "frame006.png" in str(err.value) and "\n" not in str(err.value)
    for f in (tmp_path / "out").iterdir():
        assert not f.name.startswith(".")
        if f.is_file():
            read_image(f)


def test_an_interrupted_run_leaves_complete_files_only(grey, tmp_path, monkeypatch):
    X, folder, _ = grey
    from bigT.compensation import realtime

    calls = [0]
    compute = realtime.Compensator.compensate_codes  # a PNG folder's codes path

    def interrupted(self, *args, **kwargs):  # Ctrl-C in the products, frames being encoded
        calls[0] += 1
        if calls[0] == 5:
            raise KeyboardInterrupt
        return compute(self, *args, **kwargs)

    monkeypatch.setattr(realtime.Compensator, "compensate_codes", interrupted)
    with FileCompensation(X, folder, tmp_path / "out", batch=1) as job:
        with pytest.raises(KeyboardInterrupt):
            job.run()
    # frames 0-3 were handed to the encoders: those started are finished, the others
    # dropped; nothing else is there, nothing half written
    left = sorted((tmp_path / "out").iterdir())
    assert {f.name for f in left} <= {f"frame{i:03d}.png" for i in range(4)}
    for f in left:
        read_image(f)


def test_each_frame_is_fsynced_before_its_rename_and_the_folder_once_after_the_last(
        grey, tmp_path, monkeypatch):
    """Crash safety at one fsync of the folder per run: every frame's file is flushed
    before the rename that publishes it (whole or absent after a power cut), and the
    folder once, after the last rename (each rename durable when the run returns)."""
    import os

    X, folder, _ = grey
    out = tmp_path / "out"
    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        events.append(("fsync", os.path.realpath(f"/proc/self/fd/{fd}")))
        return real_fsync(fd)

    def replace(src, dst, **kw):
        events.append(("rename", os.path.realpath(src), os.path.realpath(dst)))
        return real_replace(src, dst, **kw)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    compensate_files(X, folder, out, batch=1)
    renames = [e for e in events if e[0] == "rename" and os.path.dirname(e[2]) == str(out)]
    assert len(renames) == FRAMES
    for _, tmp, _dst in renames:  # the file flushed before it is published
        flushed = events.index(("fsync", tmp))
        assert flushed < events.index(("rename", tmp, _dst))
    folder_syncs = [k for k, e in enumerate(events) if e == ("fsync", str(out.resolve()))]
    assert len(folder_syncs) == 1, "the folder is fsynced once, not once per frame"
    assert folder_syncs[0] > max(events.index(r) for r in renames)


def test_killed_writers_files_are_cleaned_once_per_folder(grey, tmp_path, monkeypatch):
    """A temporary file a killed run left is deleted, by one scan of the output folder
    for the run (a scan per frame reads the whole folder each time: quadratic)."""
    from bigT import atomic

    X, folder, _ = grey
    out = tmp_path / "out"
    out.mkdir()
    litter = out / ".frame001.999999999@{}.0badc0de.tmp.png".format(atomic._host_tag())
    litter.write_bytes(b"half a frame")
    scans = []
    real = atomic.dead_writers_siblings
    monkeypatch.setattr(atomic, "dead_writers_siblings",
                        lambda *a, **k: scans.append(a) or real(*a, **k))
    compensate_files(X, folder, out, batch=1)
    assert not litter.exists()
    assert len(scans) == 1
    assert sorted(p.name for p in out.iterdir()) == [f"frame{i:03d}.png" for i in range(FRAMES)]


def test_the_products_leave_codec_cores_to_the_codecs(grey, tmp_path, monkeypatch):
    """With the codecs on a pool, the products take the cores less CODEC_CORES (none
    by default: every core; unless the user set config.KERNEL_THREADS), and the
    compensator's own count comes back after the run; the frames are the same whatever
    the count (rows are split, never a sum)."""
    from bigT import config
    from bigT.compensation import pipeline, realtime

    pool = CodecPool(2)
    monkeypatch.setattr(pipeline.os, "cpu_count", lambda: 2)
    assert pipeline.CODEC_CORES == 0 and pool.product_threads(2) == 2
    monkeypatch.setattr(pipeline, "CODEC_CORES", 1)
    monkeypatch.setattr(pipeline.os, "cpu_count", lambda: 8)
    assert pool.product_threads(8) == 7
    monkeypatch.setattr(pipeline.os, "cpu_count", lambda: 2)
    assert pool.product_threads(2) == 1
    monkeypatch.setattr(pipeline.os, "cpu_count", lambda: 1)
    assert pool.product_threads(1) == 1
    monkeypatch.setattr(config, "KERNEL_THREADS", 2)
    assert pool.product_threads(2) == 2
    monkeypatch.setattr(config, "KERNEL_THREADS", None)
    monkeypatch.setattr(pipeline.os, "cpu_count", lambda: 4)

    X, folder, _ = grey
    seen = []
    compute = realtime.Compensator.compensate_codes  # a PNG folder's codes path
    monkeypatch.setattr(realtime.Compensator, "compensate_codes",
                        lambda self, *a, **k: seen.append(self.threads) or compute(self, *a, **k))
    with FileCompensation(X, folder, tmp_path / "pooled", batch=1) as job:
        job.compensator.threads = 4
        job.run()
        assert set(seen) == {3} and job.compensator.threads == 4
        seen.clear()
        with FileCompensation(X, folder, tmp_path / "serial", batch=1) as serial:
            serial.compensator.threads = 4
            serial.run(overlap=False)
        assert set(seen) == {4}
    assert _files(tmp_path / "pooled") == _files(tmp_path / "serial")


@pytest.mark.parametrize("scene", ["grey", "colour"])
@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("clip", [(0, 1), (0.2, 0.5), (0, None), None])
@pytest.mark.parametrize("overlap", [True, False])
def test_png_codes_path_writes_the_float_paths_files(request, tmp_path, scene, bits, clip,
                                                     overlap):
    """A folder of plain PNG frames, X in memory, linear light: the codes go through the
    products as they are (FileCompensation.image_code_dtype) and the files written are
    the float frames', byte for byte, with the same clip counts."""
    X, _, _ = request.getfixturevalue(scene)
    shape = X.pixel_order.frame_shape
    folder = _folder(tmp_path / f"in{bits}", shape, bits=bits, seed=bits)
    # codes at the ends and past the clip, so that every branch of the quantisation runs
    write_image(folder / "frame900.png", np.where(np.indices(shape).sum(0) % 2, 1.0, 0.0),
                bits=bits)
    reports = {}
    for codes in (True, False):
        with FileCompensation(X, folder, tmp_path / f"o{codes}", batch=4, clip=clip,
                              encoding="linear") as job:
            assert job.image_code_dtype == np.dtype(f"uint{bits}")
            reports[codes] = job.run(codes=codes, overlap=overlap).compensation
    assert _files(tmp_path / "oTrue") == _files(tmp_path / "oFalse")
    assert [(r.clipped_low, r.clipped_high, r.clipped_low_by_channel, r.pixels)
            for r in reports.values()] == [(reports[False].clipped_low,
                                            reports[False].clipped_high,
                                            reports[False].clipped_low_by_channel,
                                            reports[False].pixels)] * 2


def test_png_codes_path_only_where_it_gives_the_same_files(grey, tmp_path):
    """Another depth asked for, another suffix, X streamed, frames of mixed depths, a
    palette or an alpha channel: the float frames run."""
    from PIL import Image

    X, folder, _ = grey
    for options in ({"bits": 8}, {"resident": False}):
        with FileCompensation(X, folder, tmp_path / "o", **options) as job:
            assert job.image_code_dtype is None
    shape = X.pixel_order.image_shape
    mixed = _folder(tmp_path / "mixed", shape, frames=2)
    write_image(mixed / "frame009.png", np.full(shape, 0.5), bits=8)
    palette = _folder(tmp_path / "palette", shape, frames=2, bits=8)
    Image.fromarray(np.zeros(shape, np.uint8)).convert("P").save(palette / "frame000.png")
    alpha = _folder(tmp_path / "alpha", shape, frames=2, bits=8)
    Image.fromarray(np.zeros(shape, np.uint8)).convert("LA").save(alpha / "frame000.png")
    for inputs in (mixed, palette, alpha):
        with FileCompensation(X, inputs, tmp_path / f"o-{inputs.name}") as job:
            assert job.image_code_dtype is None
            if inputs is not palette:  # (whose palette reads as RGB: refused, as before)
                job.run()  # and still runs, on the float frames


def test_image_codes_quantise_as_write_image():
    """The codes kernels' image arithmetic is bigT.images': a code's value divided in
    float32 as the reader divides it, and the quantisation of write_image (NaN, -0,
    negatives, values past 1, infinities and the half-codes between)."""
    from bigT.compensation.codes import code_values, scatter_codes
    from bigT.images import _quantised, _to_unit

    for dtype in (np.uint8, np.uint16):
        codes = np.arange(np.iinfo(dtype).max + 1, dtype=dtype)
        assert np.array_equal(code_values(dtype, images=True), _to_unit(codes, "", np.float32))
        top = float(np.iinfo(dtype).max)
        halves = ((np.arange(2000) + 0.5) / top).astype(np.float32)
        Y = np.concatenate([halves, np.nextafter(halves, 1), np.nextafter(halves, 0),
                            np.float32([np.nan, -0.0, -1e-9, 1.0, 1 + 1e-7, np.inf, -np.inf])])
        Y = Y[:, None].copy()
        perm = np.arange(Y.shape[0])
        got, below, above = scatter_codes(Y, perm, None, (Y.shape[0],), dtype, images=True)
        np.testing.assert_array_equal(got[0], _quantised(Y[:, 0], 8 * np.dtype(dtype).itemsize))
        assert (below, above) == (0, 0)


def test_png_code_dtype_leaves_an_unreadable_frame_to_the_float_reader(tmp_path):
    """A frame gone (or unreadable) when the headers are read: no codes path (None),
    so the float frames' reader names the file in its one-line ImageError."""
    from bigT.images import png_code_dtype, write_image

    ok = write_image(tmp_path / "a.png", np.zeros((4, 4)), bits=16)
    assert png_code_dtype([ok]) == np.dtype(np.uint16)
    assert png_code_dtype([ok, tmp_path / "gone.png"]) is None
