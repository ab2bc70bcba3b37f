"""compensate through a projector's response (issue #29, point 1): the projector's
integer values, dithered or not, the clipping counted, the simulation closed through the
same nonlinear projector; and without a response, the output says so."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT.calibration import NonlinearRig, fit_projector_response
from bigT.cli import main
from bigT.compensation import FileCompensation, FileSimulation
from bigT.compensation.projector import ProjectorEncoder
from bigT.images import read_image, write_image

from comp_helpers import random_transport

H, W = 10, 12
LEVELS = np.linspace(0.0, 1.0, 17)


def gamma_response(channels=1, black=0.02):
    """A gamma-2.2 response with a black level, fitted from its exact ramp."""
    light = black + (1 - black) * LEVELS ** 2.2
    return fit_projector_response(LEVELS, light if channels == 1
                                  else np.repeat(light[:, None], channels, axis=1))


def float64_store(A, path, shape):
    """A float64 store: the streamed products are float64, as the reference's."""
    return bigT.from_scipy(sp.csr_array(A), path, tile_size=48, image_shape=shape,
                           input_order="row-major", dtype="float64")


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("projector")
    T, X, F, A = random_transport(H, W, seed=3)
    float64_store(T, d / "T.zarr", (H, W))
    float64_store(X, d / "X.zarr", (H, W))
    response = gamma_response()
    response.save(d / "response.json")
    return d, T, X, response


@pytest.mark.parametrize("bits,dither", [(8, "none"), (16, "none"), (8, "ordered"),
                                         (16, "random")])
def test_codes_are_calibrations_encode_of_the_dense_compensation(scene, tmp_path, bits,
                                                                 dither):
    d, T, X, response = scene
    desired = np.random.default_rng(1).uniform(0.05, 0.7, (H, W))
    write_image(tmp_path / "d.npy", desired)
    with FileCompensation(d / "X.zarr", tmp_path / "d.npy", tmp_path / "p.png",
                          resident=False, projector_response=d / "response.json",
                          projector_bits=bits, dither=dither, seed=4) as job:
        report = job.run()
    desired = read_image(tmp_path / "d.npy")  # as stored: float32 values
    linear = (X @ desired.ravel()).reshape(1, H, W)  # unclipped: the encoding clips
    expected = response.encode(linear, bits, dither, seed=4, above_black=True)[0]
    top = (1 << bits) - 1
    codes = np.rint(read_image(tmp_path / "p.png") * top).astype(np.int64)
    assert np.array_equal(codes, expected.astype(np.int64))
    clipping = report.projector
    assert clipping.below == (int(np.sum(linear < 0)),)
    assert clipping.above == (int(np.sum(linear > 1)),)
    assert report.clip is None  # the response's own range clips, and counts


def test_colour_encoder_matches_calibration_per_channel():
    rng = np.random.default_rng(2)
    light = np.stack([0.01 + 0.99 * LEVELS ** g for g in (2.0, 2.2, 2.5)], axis=1)
    response = fit_projector_response(LEVELS, light)
    frames = rng.uniform(-0.1, 1.1, (2, 9, 11, 3))
    for bits in (8, 16):
        for dither in ("none", "ordered"):
            encoder = ProjectorEncoder(response, bits, dither)
            assert np.array_equal(encoder.encode(frames),
                                  response.encode(frames, bits, dither, above_black=True))
            assert encoder.clipping.below == tuple(int(np.sum(frames[..., c] < 0))
                                                   for c in range(3))


def test_ordered_dither_keeps_the_mean_light():
    response = gamma_response()
    wanted = 0.1234  # between two 8-bit codes' light
    frames = np.full((1, 64, 64), wanted)
    encoder = ProjectorEncoder(response, 8, "ordered")
    dithered = encoder.emitted(encoder.encode(frames)).mean()
    rounded = ProjectorEncoder(response, 8, "none")
    plain = rounded.emitted(rounded.encode(frames)).mean()
    codes = encoder.encode(frames)
    step = float(np.ptp(encoder.emitted(np.array([codes.min(), codes.max()]))))
    assert codes.max() == codes.min() + 1  # two codes, mixed
    assert abs(dithered - wanted) <= step / 64
    assert abs(dithered - wanted) < abs(plain - wanted)


def test_emitted_is_the_response_above_black():
    response = gamma_response()
    encoder = ProjectorEncoder(response, 8)
    codes = np.arange(256, dtype=np.uint8)
    np.testing.assert_allclose(encoder.emitted(codes),
                               response.to_linear(codes / 255.0, above_black=True), atol=1e-12)


def test_simulation_through_the_projector_closes_the_loop(scene, tmp_path):
    """The camera's view is T times the light the codes send: with the response, the
    seen error is that of the linear compensation plus the 8-bit quantisation; the same
    linear values sent to the gamma projector as codes are far off."""
    d, T, X, response = scene
    desired = np.full((H, W), 0.3)
    write_image(tmp_path / "d.npy", desired)
    job = FileSimulation(d / "X.zarr", tmp_path / "d.npy", tmp_path / "p.png", d / "T.zarr",
                         projector_response=d / "response.json", dither="ordered",
                         metrics=False)
    report = job.run()
    codes = np.rint(read_image(tmp_path / "p.png") * 255).astype(np.int64)
    light = response.to_linear(codes / 255.0, above_black=True)
    seen = read_image(tmp_path / "p_seen.png")
    expected_seen = (T @ light.ravel()).reshape(H, W)
    np.testing.assert_allclose(seen, np.clip(expected_seen, 0, 1), atol=1 / 255)
    error_with = report.simulation.error
    assert error_with < 0.01
    linear = np.clip(X @ desired.ravel(), 0, 1)  # sent as codes, no response
    uncalibrated = T @ response.to_linear(np.rint(linear * 255) / 255, above_black=True)
    error_without = np.linalg.norm(uncalibrated - desired.ravel()) / np.linalg.norm(desired)
    assert error_without > 10 * error_with


def test_nonlinear_rig_projector_seen_error(tmp_path):
    """The NonlinearRig's projector (gamma, black, shoulder), its response fitted from a
    ramp: compensation through it is within 1.5x of a linear projector's seen error."""
    rig = NonlinearRig()
    response = fit_projector_response(LEVELS, rig.project(LEVELS))
    T, X, F, A = random_transport(H, W, seed=5)
    desired = np.random.default_rng(6).uniform(0.2, 0.5, (1, H, W))
    linear = np.clip(X @ desired.reshape(-1), 0, 1)
    ideal = np.linalg.norm(T @ linear - desired.ravel())  # a linear projector, no quantisation
    encoder = ProjectorEncoder(response, 8, "ordered")
    codes = encoder.encode(linear.reshape(1, H, W))
    b = rig.project(0.0)
    sent = (rig.project(codes / 255.0) - b) / (1 - b)  # the true projector's light
    calibrated = np.linalg.norm(T @ sent.ravel() - desired.ravel())
    raw = (rig.project(np.rint(linear * 255) / 255) - b) / (1 - b)
    uncalibrated = np.linalg.norm(T @ raw - desired.ravel())
    ref = np.linalg.norm(desired)
    assert calibrated / ref < 0.01
    assert uncalibrated > 10 * calibrated
    assert ideal <= calibrated


def test_cli_says_which_response_or_none(scene, tmp_path, capsys):
    d, T, X, response = scene
    write_image(tmp_path / "d.npy", np.full((H, W), 0.4))
    assert main(["compensate", str(d / "X.zarr"), str(tmp_path / "d.npy"), "-o",
                 str(tmp_path / "p.npy"), "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert ("no projector response: writing linear light encoded as linear, not projector "
            "values -- see Calibrating a rig") in text
    assert main(["compensate", str(d / "X.zarr"), str(tmp_path / "d.npy"), "-o",
                 str(tmp_path / "p.png"), "--projector-response", str(d / "response.json"),
                 "--dither", "ordered", "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert (f"projector response {d / 'response.json'} (black 0.02, 8-bit, dithered "
            "ordered)") in text
    assert "clipped by the projector's response" in text and "below black" in text
    assert "wrote the projector's values (8-bit" in text


def test_cli_refuses_projector_bits_without_a_response(scene, tmp_path, capsys):
    d, T, X, response = scene
    write_image(tmp_path / "d.npy", np.full((H, W), 0.4))
    assert main(["compensate", str(d / "X.zarr"), str(tmp_path / "d.npy"), "-o",
                 str(tmp_path / "p.png"), "--projector-bits", "16", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "needs a projector response" in err and "--projector-bits 16" in err
    assert len(err.strip().splitlines()) == 1
    assert main(["compensate", str(d / "X.zarr"), str(tmp_path / "d.npy"), "-o",
                 str(tmp_path / "p.png"), "--projector-response", str(d / "response.json"),
                 "--bits", "16", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "disagrees" in err and "--projector-bits 16" in err
    assert not (tmp_path / "p.png").exists()


def test_response_stored_with_T_is_found(scene, tmp_path, capsys):
    d, T, X, response = scene
    stored = tmp_path / "T.zarr"
    float64_store(T, stored, (H, W))
    response.save(stored / "projector_response.json")
    write_image(tmp_path / "d.npy", np.full((H, W), 0.4))
    assert main(["compensate", "-", str(tmp_path / "d.npy"), "-o", str(tmp_path / "p.png"),
                 "--matrix-free", str(stored), "--no-progress"]) == 0
    assert "projector_response.json, stored with T, (black 0.02" in capsys.readouterr().out
    assert main(["compensate", "-", str(tmp_path / "d.npy"), "-o", str(tmp_path / "q.npy"),
                 "--matrix-free", str(stored), "--projector-response", "none",
                 "--no-progress"]) == 0
    assert "no projector response" in capsys.readouterr().out
