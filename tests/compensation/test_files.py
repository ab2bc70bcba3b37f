"""bigT.compensation.files: what `bigT compensate` does, called from Python, against a
dense numpy reference (the row-major matrices the stores were written from)."""

from __future__ import annotations

import numpy as np
import pytest

from bigT.compensation import (FileCompensation, FileCompensationReport, compensate_files,
                               relight_files)
from bigT.errors import ImageError

from comp_helpers import make_store


@pytest.fixture()
def stores(tmp_path, small_scene):
    s = small_scene
    shape = (s["H"], s["W"])
    X = make_store(s["X"], tmp_path / "X.zarr", image_shape=shape, tile_size=32,
                   pixel_order="tile-major")
    T = make_store(s["T"], tmp_path / "T.zarr", image_shape=shape, tile_size=32,
                   pixel_order="tile-major")
    return s, X, T


def _desired(s, k, seed=1):
    rng = np.random.default_rng(seed)
    return rng.uniform(0.05, 0.95, (k, s["H"], s["W"]))


def test_one_image_matches_dense_numpy(tmp_path, stores):
    s, X, _ = stores
    desired = _desired(s, 1)[0]
    np.save(tmp_path / "desired.npy", desired)
    report = compensate_files(X, tmp_path / "desired.npy", tmp_path / "out.npy")

    expected = s["X"] @ desired.ravel()  # float64 reference, row-major numbering
    got = np.load(tmp_path / "out.npy")
    np.testing.assert_allclose(got.ravel(), np.clip(expected, 0, 1), atol=2e-6)
    assert isinstance(report, FileCompensationReport)
    assert report.stream.frames == 1 and report.output == tmp_path / "out.npy"
    low, high = int((expected < 0).sum()), int((expected > 1).sum())
    assert (report.compensation.clipped_low, report.compensation.clipped_high) == (low, high)
    assert report.compensation.pixels == expected.size
    assert "wrote projector input" in report.describe()


def test_a_folder_through_the_matrix_free_path(tmp_path, stores):
    s, X, T = stores
    frames = _desired(s, 3, seed=2)
    (tmp_path / "in").mkdir()
    for i, f in enumerate(frames):
        np.save(tmp_path / "in" / f"f{i}.npy", f)
    with FileCompensation(None, tmp_path / "in", tmp_path / "out", T=T, path="matrix-free",
                          terms=40, clip=None, batch=2) as job:
        assert job.frames == 3 and "path: matrix-free (40 terms)" in job.describe()
        report = job.run(overlap=False)
    assert report.stream.frames == 3 and report.clip is None
    for i, f in enumerate(frames):  # 40 terms of a series with rho < 0.4: the inverse
        got = np.load(tmp_path / "out" / f"f{i}.npy")
        np.testing.assert_allclose(got.ravel(), s["X"] @ f.ravel(), atol=1e-5)


def test_inputs_are_checked_before_anything_is_written(tmp_path, stores):
    s, X, _ = stores
    (tmp_path / "in").mkdir()
    np.save(tmp_path / "in" / "a.npy", _desired(s, 1)[0])
    np.save(tmp_path / "in" / "b.npy", np.zeros((3, 4)))  # one bad frame of a folder
    with pytest.raises(ImageError, match="b.npy"):
        FileCompensation(X, tmp_path / "in", tmp_path / "out")
    np.save(tmp_path / "ok.npy", _desired(s, 1)[0])
    with pytest.raises(ImageError, match="unknown output format '.xyz'"):
        FileCompensation(X, tmp_path / "ok.npy", tmp_path / "out.xyz")
    np.save(tmp_path / "small.npy", np.zeros((3, 4)))  # one image: refused from its header
    with pytest.raises(ImageError, match="small.npy"):
        FileCompensation(X, tmp_path / "small.npy", tmp_path / "out.npy")
    assert not any((tmp_path / name).exists() for name in ("out", "out.xyz", "out.npy"))


def test_run_outside_the_context_is_refused(tmp_path, stores):
    s, X, _ = stores
    np.save(tmp_path / "ok.npy", _desired(s, 1)[0])
    job = FileCompensation(X, tmp_path / "ok.npy", tmp_path / "out.npy")
    with pytest.raises(RuntimeError, match="context manager"):
        job.run()


def test_relight_files_matches_dense_numpy(tmp_path, stores):
    s, _, T = stores
    frames = _desired(s, 2, seed=3) * 3  # bright enough that some light exceeds 1
    (tmp_path / "in").mkdir()
    for i, f in enumerate(frames):
        np.save(tmp_path / "in" / f"f{i}.npy", f)
    report = relight_files(T, tmp_path / "in", tmp_path / "out", batch=1)
    seen = [s["T"] @ f.ravel() for f in frames]
    for i, want in enumerate(seen):
        np.testing.assert_allclose(np.load(tmp_path / "out" / f"f{i}.npy").ravel(), want,
                                   rtol=1e-5, atol=1e-6)
    above = sum(int((w > 1).sum()) for w in seen) / sum(w.size for w in seen)
    assert report.frames == 2 and report.above_one == pytest.approx(above)
    assert above > 0 and not report.clipped_in_output  # .npy keeps them
    assert "2 frame(s)" in report.describe() and "clipped" not in report.describe()


def test_file_simulation_matches_dense_numpy(tmp_path, stores):
    """compensate --simulate as a library call: the projector image and the camera's
    view written beside it, the errors against dense numpy."""
    from bigT.compensation import FileSimulation

    s, X, T = stores
    desired = _desired(s, 1, seed=4)[0]
    np.save(tmp_path / "d.npy", desired)
    job = FileSimulation(X, tmp_path / "d.npy", tmp_path / "out.npy", T, path="explicit")
    assert "path: explicit" in job.describe()
    report = job.run()
    l_in = np.clip(s["X"] @ desired.ravel(), 0, 1)
    seen = s["T"] @ l_in
    np.testing.assert_allclose(np.load(report.projector).ravel(), l_in, atol=2e-6)
    np.testing.assert_allclose(np.load(report.seen).ravel(), seen, atol=2e-5)
    assert report.seen == tmp_path / "out_seen.npy"
    want = np.linalg.norm(seen - desired.ravel()) / np.linalg.norm(desired)
    assert report.simulation.error == pytest.approx(want, rel=1e-3)
    assert all(f.exists() and f.suffix == ".png" for f in report.figures)
