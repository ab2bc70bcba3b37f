"""The projector's response: fitted from a simulated ramp against the rig's true curve,
inverted, encoded into 8/16-bit codes (dithered or not), and refused when the ramp is
not monotone or is flat."""

from __future__ import annotations

import numpy as np
import pytest

from bigT.calibration import (CameraResponse, NonlinearRig, ProjectorResponse,
                              fit_projector_response, load_projector_response)
from bigT.errors import CalibrationError

PATCH = (48, 48)   # camera pixels averaged per ramp level
ALBEDO = 0.8       # the screen's reflectance: full scale fills 0.8 of the full well


def ramp_means(rig: NonlinearRig, levels: np.ndarray, channels: int = 1) -> np.ndarray:
    """Each uniform frame's mean linear camera signal, shape (L, C)."""
    shape = PATCH if channels == 1 else PATCH + (channels,)
    values = np.ones(shape)
    means = []
    for i, v in enumerate(levels):
        radiance = ALBEDO * rig.project(v * values)
        linear = rig.camera.to_linear(rig.capture(radiance, 1.0, frame=i))
        means.append(linear.reshape(-1, channels).mean(axis=0))
    return np.array(means)


def mean_noise(rig: NonlinearRig, levels: np.ndarray) -> np.ndarray:
    """Standard deviation of a ramp mean, normalised to full scale, from the rig's noise
    model: shot, read and the camera's quantisation (a step of f^-1 between codes,
    uniform: step / sqrt 12), over the patch's pixels. Shape (L,)."""
    s = ALBEDO * rig.project(levels)
    top = (1 << rig.bits) - 1
    z = rig.camera.encode(s)
    step = rig.camera.to_linear(np.minimum(z + 1 / top, 1)) - rig.camera.to_linear(z)
    pixel = np.sqrt(s / rig.full_well_electrons + rig.read_noise ** 2 + step ** 2 / 12)
    return pixel / np.sqrt(np.prod(PATCH)) / (ALBEDO * rig.project(1.0))


@pytest.mark.parametrize("n_levels", [17, 33])
def test_fit_from_a_simulated_ramp_matches_the_true_curve(n_levels):
    """Tolerance, reasoned: the fit of the *noiseless* ramp at these levels (PCHIP's
    interpolation error, a property of the level spacing alone) plus 6 standard
    deviations of a ramp mean (a node's error passes through PCHIP about one to one,
    and the monotone projection only shrinks it)."""
    rig = NonlinearRig(seed=n_levels)
    levels = np.linspace(0.0, 1.0, n_levels)
    fitted = fit_projector_response(levels, ramp_means(rig, levels))
    exact = fit_projector_response(levels, rig.project(levels))
    grid = np.linspace(0.0, 1.0, 2001)
    truth = rig.project(grid)
    interpolation_error = np.abs(exact.to_linear(grid) - truth).max()
    tolerance = interpolation_error + 6 * mean_noise(rig, levels).max()
    error = np.abs(fitted.to_linear(grid) - truth).max()
    print(f"\n{n_levels} levels: max abs error {error:.2e} (interpolation alone "
          f"{interpolation_error:.2e}, tolerance {tolerance:.2e}); black "
          f"{fitted.black[0]:.4f} vs {rig.projector_black}")
    assert error <= tolerance
    assert fitted.to_linear(1.0) == pytest.approx(1.0)
    assert fitted.black[0] == pytest.approx(rig.projector_black, abs=6 * mean_noise(rig, levels)[0])
    assert np.all(np.diff(fitted.to_linear(grid)) >= 0)


def test_colour_ramp_fits_each_channel_its_own_curve():
    rig = NonlinearRig(projector_gamma=(2.0, 2.2, 2.5), projector_black=(0.01, 0.02, 0.04),
                       projector_shoulder=(0.1, 0.3, 0.5), seed=9)
    levels = np.linspace(0.0, 1.0, 17)
    fitted = fit_projector_response(levels, ramp_means(rig, levels, channels=3))
    assert fitted.channels == ("R", "G", "B")
    grid = np.linspace(0.0, 1.0, 501)
    truth = rig.project(np.repeat(grid[:, None], 3, axis=1))
    exact = fit_projector_response(levels, rig.project(np.repeat(levels[:, None], 3, axis=1)))
    interpolation_error = np.abs(exact.to_linear(np.repeat(grid[:, None], 3, 1)) - truth).max()
    error = np.abs(fitted.to_linear(np.repeat(grid[:, None], 3, axis=1)) - truth).max(axis=0)
    assert np.all(error <= interpolation_error + 6 * mean_noise(NonlinearRig(), levels).max() * 1.5)
    np.testing.assert_allclose(fitted.black, [0.01, 0.02, 0.04], atol=2e-3)


@pytest.fixture(scope="module")
def response() -> ProjectorResponse:
    rig = NonlinearRig(seed=1)
    levels = np.linspace(0.0, 1.0, 17)
    return fit_projector_response(levels, ramp_means(rig, levels))


def test_inverse_and_forward_round_trip(response):
    light = np.linspace(response.black[0], 1.0, 5001)
    np.testing.assert_allclose(response.to_linear(response.inverse(light)), light, atol=1e-9)
    values = np.linspace(0.05, 1.0, 2001)   # above the flat near-black stretch
    np.testing.assert_allclose(response.inverse(response.to_linear(values)), values, atol=1e-6)
    above = np.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(
        response.to_linear(response.inverse(above, above_black=True), above_black=True), above,
        atol=1e-9)
    assert response.inverse(0.0, above_black=True) == pytest.approx(0.0, abs=1e-6)
    assert response.inverse(1.0, above_black=True) == pytest.approx(1.0)


def test_out_of_range_light_is_clipped_and_counted(response):
    linear = np.array([[-0.2, 0.0, 0.5], [1.0, 1.3, 2.0]])
    clip = response.clipping(linear)
    assert (clip.below, clip.above, clip.size) == ((2,), (2,), 6)
    values = response.inverse(linear)
    assert values.min() == 0.0 and values.max() == 1.0
    assert response.clipping(linear, above_black=True).below == (1,)
    assert "2 values below black, 2 above full scale" in clip.describe()


@pytest.mark.parametrize("bits", [8, 16])
def test_encode_sends_the_code_whose_true_light_is_nearest(bits):
    """Checked through the rig's true projector, not the fit: the light of the code
    sent is within half a code step (in light) of the wanted light, plus the fit's
    error."""
    rig = NonlinearRig(seed=2)
    levels = np.linspace(0.0, 1.0, 33)
    response = fit_projector_response(levels, rig.project(levels))  # noiseless ramp
    grid = np.linspace(0.0, 1.0, 4001)
    fit_error = np.abs(response.to_linear(grid) - rig.project(grid)).max()
    wanted = np.linspace(rig.projector_black, 1.0, 3000).reshape(30, 100)
    codes = response.encode(wanted, bits=bits)
    top = (1 << bits) - 1
    assert codes.dtype == (np.uint8 if bits == 8 else np.uint16) and codes.shape == wanted.shape
    codes = codes.astype(np.int64)
    sent = rig.project(codes / top)
    # half the step to a neighbouring code, the wider of the two sides
    half_step = np.maximum(rig.project(np.minimum(codes + 1, top) / top) - sent,
                           sent - rig.project(np.maximum(codes - 1, 0) / top)) / 2
    assert np.all(np.abs(sent - wanted) <= half_step + 2 * fit_error)


@pytest.mark.parametrize("kind", ["ordered", "random"])
def test_dither_preserves_the_mean_light(response, kind):
    """A uniform area of light between two 8-bit codes: rounding sends one code (an
    error of up to half a step); dithering mixes the two so that the mean light is the
    one asked -- to 1/128 of a step for the 8 x 8 Bayer matrix over whole tiles, to 5
    sigma of a Bernoulli mean for random thresholds."""
    top = 255
    for code, fraction in [(40, 0.3), (128, 0.5), (200, 0.85)]:
        low, high = response.to_linear(np.array([code, code + 1]) / top)
        wanted = low + fraction * (high - low)
        area = np.full((64, 64), wanted)
        rounded = response.to_linear(response.encode(area) / top).mean()
        dithered = response.encode(area, dither=kind, seed=3)
        assert set(np.unique(dithered)) <= {code, code + 1}
        mean = response.to_linear(dithered / top).mean()
        step = high - low
        bound = step / 128 if kind == "ordered" else 5 * step * np.sqrt(
            fraction * (1 - fraction) / area.size)
        assert abs(mean - wanted) <= bound
        assert abs(rounded - wanted) >= min(fraction, 1 - fraction) * step * 0.99


def test_colour_encode_and_dither_keep_the_channel_axis():
    levels = np.linspace(0.0, 1.0, 17)
    curves = np.stack([0.02 + 0.98 * levels ** g for g in (2.0, 2.2, 2.4)], axis=1)
    response = fit_projector_response(levels, curves)
    image = np.random.default_rng(0).uniform(0.05, 1.0, (6, 10, 3))
    for dither in (False, True, "random"):
        codes = response.encode(image, bits=16, dither=dither)
        assert codes.shape == (6, 10, 3) and codes.dtype == np.uint16
        np.testing.assert_allclose(response.to_linear(codes / 65535.0), image, atol=1e-3)
    with pytest.raises(CalibrationError, match="last axis must have 3"):
        response.encode(np.zeros((6, 10)))


def test_bad_encode_arguments_are_refused(response):
    with pytest.raises(CalibrationError, match="8 or 16, not 12"):
        response.encode(np.zeros((2, 2)), bits=12)
    with pytest.raises(CalibrationError, match="unknown dither 'blue'"):
        response.encode(np.zeros((2, 2)), dither="blue")


def one_line(error: pytest.ExceptionInfo) -> str:
    text = str(error.value)
    assert "\n" not in text
    return text


def test_a_ramp_not_monotone_beyond_the_noise_is_refused_naming_channel_and_levels():
    levels = np.linspace(0.0, 1.0, 17)
    curves = np.stack([0.02 + 0.98 * levels ** 2.2] * 3, axis=1)
    curves[9, 1] = curves[8, 1] - 0.05   # G falls from level 0.5 to 0.5625
    with pytest.raises(CalibrationError) as error:
        fit_projector_response(levels, curves)
    assert one_line(error).startswith(
        "ramp not monotone in channel G between levels 0.5 and 0.5625")


def test_a_fall_within_the_noise_is_fitted_monotone():
    levels = np.linspace(0.0, 1.0, 17)
    means = 0.02 + 0.98 * levels ** 2.2
    means[1] = means[0] - 1e-4  # near black, a gamma ramp hardly rises: noise
    response = fit_projector_response(levels, means, noise=1e-4)
    assert np.all(np.diff(response.output[:, 0]) >= 0)


@pytest.mark.parametrize("means, problem", [
    (np.full(17, 0.4), "ramp flat in channel grey: full scale is 1x the black level"),
    (0.3 + 0.1 * np.linspace(0, 1, 17), "ramp flat in channel grey: full scale is 1.33x"),
    (np.zeros(17), "ramp flat in channel grey: full scale is no brighter than"),
])
def test_a_flat_ramp_is_refused(means, problem):
    with pytest.raises(CalibrationError) as error:
        fit_projector_response(np.linspace(0.0, 1.0, 17), means)
    assert one_line(error).startswith(problem)


@pytest.mark.parametrize("levels, problem", [
    (np.linspace(0, 1, 9), "a ramp of 9 levels: it needs 17"),
    (np.linspace(0.1, 1, 17), "must increase strictly from 0 to 1"),
    (np.r_[np.linspace(0, 0.5, 9), np.linspace(0.5, 1, 8)], "must increase strictly"),
])
def test_bad_ramp_levels_are_refused(levels, problem):
    with pytest.raises(CalibrationError, match=problem):
        fit_projector_response(levels, np.linspace(0.02, 1, levels.size))


def test_save_load_and_draw(response, tmp_path):
    saved = response.save(tmp_path / "projector.json")
    loaded = load_projector_response(saved)
    np.testing.assert_array_equal(loaded.output, response.output)
    np.testing.assert_array_equal(loaded.measured, response.measured)
    grid = np.linspace(0, 1, 101)
    np.testing.assert_array_equal(loaded.to_linear(grid), response.to_linear(grid))
    png = response.draw(tmp_path / "projector.png")
    import imageio.v3 as iio

    picture = iio.imread(png)
    assert picture.ndim == 3 and picture.shape[0] > 200
    # the curve is drawn: the picture is not one colour
    assert picture[..., :3].std() > 10


def test_rig_camera_default_is_gamma():
    assert NonlinearRig().camera == CameraResponse("gamma", gamma=2.2, source="any label")
    assert NonlinearRig().camera != CameraResponse("gamma", gamma=2.4)
    table = np.linspace(0, 1, 256)
    assert CameraResponse("table", table=table) == CameraResponse("table", table=table.copy())
    assert CameraResponse("table", table=table) != CameraResponse("table", table=table ** 2)
