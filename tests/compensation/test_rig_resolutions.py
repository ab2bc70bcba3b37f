"""The rig's resolutions end to end (issue #29, point 5): a camera-size desired image in,
averaged onto the camera super-pixels through the stored correspondence, the
projector's full image out; refusals naming both accepted sizes."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT.cli import main
from bigT.compensation import FileCompensation, FileSimulation
from bigT.compensation.rig import load_correspondence, recorded_transport, rig_geometry
from bigT.images import read_image, write_image
from bigT.storage import InverseStore
from bigT.storage.inverse_store import InverseRecord

from comp_helpers import random_transport

GRID = (3, 4)          # super-pixels: T's images
S = 2                  # super-pixel side: the projector is 6 x 8
CAMERA = (5, 7)


def labels_for_camera():
    """Each camera pixel's super-pixel (row-major on GRID), -1 on the border column,
    as acquire build's correspondence holds them."""
    rows = np.minimum(np.arange(CAMERA[0]) * GRID[0] // CAMERA[0], GRID[0] - 1)
    cols = np.minimum(np.arange(CAMERA[1] - 1) * GRID[1] // (CAMERA[1] - 1), GRID[1] - 1)
    labels = np.full(CAMERA, -1, np.int32)
    labels[:, :-1] = rows[:, None] * GRID[1] + cols[None, :]
    return labels


def acquired_store(T, path, channels=1):
    """A T store as acquire build leaves it: its settings in the metadata, the
    correspondence in ``acquisition/correspondence.npy``."""
    meta = {"acquisition": {"projector": [GRID[0] * S, GRID[1] * S], "superpixel": S,
                            "camera": list(CAMERA), "method": "brute-force"}}
    store = bigT.from_scipy(sp.csr_array(T), path, tile_size=12 if channels == 1 else 36,
                            image_shape=GRID, input_order="row-major", dtype="float64",
                            metadata=meta, channels=channels)
    (path / "acquisition").mkdir()
    np.save(path / "acquisition" / "correspondence.npy", labels_for_camera())
    return store


def averaging_matrix():
    """(grid pixels, camera pixels): the mean of each group's camera pixels."""
    labels = labels_for_camera().ravel()
    M = np.zeros((GRID[0] * GRID[1], labels.size))
    for g in range(M.shape[0]):
        members = labels == g
        M[g, members] = 1.0 / members.sum()
    return M


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    d = tmp_path_factory.mktemp("rig")
    T, X, F, A = random_transport(*GRID, seed=11, density=0.3)
    acquired_store(T, d / "T.zarr")
    bigT.from_scipy(sp.csr_array(X), d / "X.zarr", tile_size=12, image_shape=GRID,
                    input_order="row-major", dtype="float64")
    return d, T, X


def test_geometry_read_from_the_store(rig):
    d, T, X = rig
    g = rig_geometry(bigT.open(d / "T.zarr"))
    assert g.camera == CAMERA and g.grid == GRID and g.projector == (6, 8)
    assert g.describe() == "camera image 5x7 -> 3x4 super-pixels -> projector 6x8"
    assert np.array_equal(load_correspondence(d / "T.zarr"), labels_for_camera())
    assert rig_geometry(bigT.open(d / "X.zarr")) is None  # records no rig


def test_camera_image_in_projector_image_out(rig, tmp_path):
    d, T, X = rig
    camera = np.random.default_rng(0).uniform(0.2, 0.6, CAMERA)
    write_image(tmp_path / "want.npy", camera)
    camera = read_image(tmp_path / "want.npy")
    with FileCompensation(d / "X.zarr", tmp_path / "want.npy", tmp_path / "p.npy",
                          T=d / "T.zarr", path="explicit", resident=False) as job:
        assert "camera image 5x7 -> 3x4 super-pixels -> projector 6x8" in job.describe()
        job.run()
    out = read_image(tmp_path / "p.npy")
    assert out.shape == (6, 8)
    superpixels = np.clip(X @ (averaging_matrix() @ camera.ravel()), 0, 1).reshape(GRID)
    expected = np.repeat(np.repeat(superpixels, S, axis=0), S, axis=1)
    np.testing.assert_allclose(out, expected, rtol=1e-6, atol=1e-7)


def test_smooth_projector_image_is_bilinear_between_centres(rig, tmp_path):
    d, T, X = rig
    write_image(tmp_path / "want.npy", np.full(GRID, 0.3))  # the super-pixels' own size
    with FileCompensation(d / "X.zarr", tmp_path / "want.npy", tmp_path / "p.npy",
                          T=d / "T.zarr", path="explicit", smooth=True) as job:
        assert "super-pixel image 3x4 -> projector 6x8 (smoothed)" in job.describe()
        job.run()
    out = read_image(tmp_path / "p.npy")
    grid = np.clip(X @ np.full(12, 0.3), 0, 1).reshape(GRID)
    # projector pixel 1 of 8 sits at centre 0.25 of super-pixel column 0..1: 3/4 col 0
    np.testing.assert_allclose(out[0, 1], 0.75 * grid[0, 0] + 0.25 * grid[0, 1], rtol=1e-5)
    np.testing.assert_allclose(out[0, 0], grid[0, 0], rtol=1e-5)  # edge held
    # pixel 2 sits at centre 0.75: a quarter of super-pixel 0, three quarters of 1
    np.testing.assert_allclose(out[2, 2], (0.25 * 0.25 * grid[0, 0] + 0.25 * 0.75 * grid[0, 1]
                                           + 0.75 * 0.25 * grid[1, 0] + 0.75 * 0.75 * grid[1, 1]),
                               rtol=1e-5)


def test_simulation_round_trip_at_the_camera(rig, tmp_path):
    d, T, X = rig
    camera = np.full(CAMERA, 0.3)
    write_image(tmp_path / "want.npy", camera)
    report = FileSimulation(d / "X.zarr", tmp_path / "want.npy", tmp_path / "p.npy",
                            d / "T.zarr", path="explicit", metrics=False).run()
    assert read_image(tmp_path / "p.npy").shape == (6, 8)
    seen = read_image(tmp_path / "p_seen.npy")
    assert seen.shape == CAMERA
    assert np.all(seen[:, -1] == 0)  # outside every group
    np.testing.assert_allclose(seen[:, :-1], 0.3, atol=1e-5)  # X is T's exact inverse
    assert report.simulation.error < 1e-5


def test_colour_camera_image(tmp_path):
    rng = np.random.default_rng(3)
    n = GRID[0] * GRID[1] * 3
    T = np.eye(n) * 0.8 + rng.uniform(0, 0.01, (n, n))
    acquired_store(T, tmp_path / "T.zarr", channels=3)
    bigT.from_scipy(sp.csr_array(np.linalg.inv(T)), tmp_path / "X.zarr", tile_size=36,
                    image_shape=GRID, input_order="row-major", dtype="float64", channels=3)
    camera = rng.uniform(0.1, 0.5, (*CAMERA, 3))
    write_image(tmp_path / "want.npy", camera)
    camera = read_image(tmp_path / "want.npy")
    with FileCompensation(tmp_path / "X.zarr", tmp_path / "want.npy", tmp_path / "p.npy",
                          T=tmp_path / "T.zarr", path="explicit", encoding="linear") as job:
        job.run()
    out = read_image(tmp_path / "p.npy")
    assert out.shape == (6, 8, 3)
    means = np.stack([averaging_matrix() @ camera[..., c].ravel() for c in range(3)], axis=1)
    superpixels = np.clip(np.linalg.inv(T) @ means.ravel(), 0, 1).reshape(*GRID, 3)
    np.testing.assert_allclose(out[::S, ::S], superpixels, rtol=1e-5, atol=1e-6)


def test_wrong_size_is_refused_naming_both_sizes(rig, tmp_path, capsys):
    d, T, X = rig
    write_image(tmp_path / "projector_size.png", np.zeros((6, 8)))
    rc = main(["compensate", str(d / "X.zarr"), str(tmp_path / "projector_size.png"), "-o",
               str(tmp_path / "p.png"), "--matrix-free", str(d / "T.zarr"), "--path",
               "explicit", "--no-progress"])
    assert rc == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "is 6x8" in err and "5x7" in err and "3x4" in err
    assert not (tmp_path / "p.png").exists()


def test_T_found_through_X_record(rig, tmp_path, capsys):
    """An X whose record names its T (what bigT invert writes, bigT info shows) finds
    the rig without being told."""
    d, T, X = rig
    xs = bigT.from_scipy(sp.csr_array(X), tmp_path / "X.zarr", tile_size=12,
                         image_shape=GRID, input_order="row-major", dtype="float64")
    InverseStore(xs.path).save(InverseRecord({"T": {"path": str((d / "T.zarr").resolve())}}))
    assert recorded_transport(bigT.open(tmp_path / "X.zarr")) == (d / "T.zarr").resolve()
    write_image(tmp_path / "want.npy", np.full(CAMERA, 0.3))
    assert main(["compensate", str(tmp_path / "X.zarr"), str(tmp_path / "want.npy"), "-o",
                 str(tmp_path / "p.npy"), "--no-progress"]) == 0
    assert "camera image 5x7 -> 3x4 super-pixels -> projector 6x8" in capsys.readouterr().out
    assert read_image(tmp_path / "p.npy").shape == (6, 8)
