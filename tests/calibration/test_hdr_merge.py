"""Exposure brackets of the simulated nonlinear rig merged into radiance spanning
1e-4 .. 1, against the radiance the rig was given; the camera response recovered
by OpenCV (Debevec, Robertson) against the rig's true gamma; bad brackets refused."""

from __future__ import annotations

import numpy as np
import pytest

from bigT.calibration import (CameraResponse, NonlinearRig, check_bracket, merge_bracket,
                              recover_camera_response)
from bigT.errors import CalibrationError

SHORTEST = 0.9  # s: radiance 1 fills 0.9 of the full well, unsaturated
RATIO = 8.0     # three stops between exposures
DECADES = (-4, -3, -2, -1)


def radiance_map(rows: int = 64, columns: int = 400) -> np.ndarray:
    """Radiance log-uniform from 1e-4 to 1 along the columns, one row per noise draw."""
    return np.tile(np.logspace(-4, 0, columns), (rows, 1))


def relative_errors(rig: NonlinearRig, radiance: np.ndarray, K: int) -> np.ndarray:
    times = SHORTEST * RATIO ** np.arange(K)
    bracket = [rig.capture(radiance, t) for t in times]
    return np.abs(merge_bracket(bracket, times, rig.camera) - radiance) / radiance


def decade_p95(errors: np.ndarray, radiance: np.ndarray) -> list[float]:
    row = radiance[0]
    return [float(np.percentile(errors[:, (row >= 10.0 ** d) & (row < 10.0 ** (d + 1))], 95))
            for d in DECADES]


def predicted_sigma(rig: NonlinearRig, radiance: float, exposure: float) -> float:
    """Relative noise of one sample x / t of ``radiance`` at ``exposure``: shot, read
    and the 8-bit quantisation of the gamma-coded value (a code step in linear light,
    uniform: step / sqrt 12)."""
    s = radiance * exposure
    step = rig.camera.to_linear(min(rig.camera.encode(s) + 1 / 255, 1.0)) - s
    return float(np.sqrt(s / rig.full_well_electrons + rig.read_noise ** 2 + step ** 2 / 12) / s)


def test_brackets_of_2_3_4_exposures_beat_one_across_the_range():
    """Each added exposure (three stops longer) brings the next decade down into the
    well-exposed codes. Bounds, reasoned from the noise model: with 4 exposures every
    decade's 95th percentile is within 2.5 sigma (1.96 sigma for a Gaussian, plus
    margin for the quantisation's non-Gaussian tail) of the sigma predicted for the
    decade's darkest radiance in the longest exposure that does not saturate it; one
    exposure is more than 10x worse in the darkest decade."""
    rig = NonlinearRig(seed=5)
    radiance = radiance_map()
    table = {K: decade_p95(relative_errors(rig, radiance, K), radiance) for K in (1, 2, 3, 4)}
    print("\nK  p95 relative error per decade " + "  ".join(f"1e{d}" for d in DECADES))
    for K, row in table.items():
        print(K, "  ".join(f"{x:.4f}" for x in row))
    darkest = table[4][0]
    assert darkest < table[3][0] < table[2][0] < table[1][0]
    assert table[1][0] > 10 * darkest
    longest = SHORTEST * RATIO ** 3
    for d, p95 in zip(DECADES, table[4]):
        exposure = max(t for t in SHORTEST * RATIO ** np.arange(4)
                       if rig.camera.encode(10.0 ** (d + 1) * t) < 0.98)
        assert p95 <= 2.5 * predicted_sigma(rig, 10.0 ** d, min(exposure, longest)), d
    for K in (2, 3, 4):  # never worse than one exposure, in any decade
        assert all(a <= b * 1.05 for a, b in zip(table[K], table[1]))


def test_colour_bracket_merges_each_channel():
    rig = NonlinearRig(seed=6)
    radiance = np.stack([radiance_map(16, 100) * f for f in (1.0, 0.5, 0.25)], axis=-1)
    times = SHORTEST * RATIO ** np.arange(4)
    merged = merge_bracket([rig.to_codes(rig.capture(radiance, t)) for t in times], times,
                           rig.camera)
    assert merged.shape == radiance.shape
    assert np.percentile(np.abs(merged - radiance) / radiance, 95) < 0.06


def test_weights_favour_the_longer_exposure_where_it_is_not_saturated():
    """By hand: a pixel at z = 0.1 in 1 s and z = 0.5 in 4 s (linear camera, so 0.1
    and 0.125 per second): hats 0.08 and 0.48, weights x t: E = (0.08 * 0.1 + 0.48 *
    0.5) / (0.08 * 1 + 0.48 * 4) = 0.124. A pixel saturated in the longer exposure
    keeps the shorter one's 0.3; one below black in both keeps the longer one's."""
    images = [np.array([[0.1, 0.3, 0.01]]), np.array([[0.5, 0.99, 0.015]])]
    merged = merge_bracket(images, [1.0, 4.0], CameraResponse("linear"))
    np.testing.assert_allclose(merged, [[0.124, 0.3, 0.015 / 4]])


def test_recovered_responses_match_the_true_gamma():
    """OpenCV's Debevec and Robertson on an 8-bit bracket of 7 exposures one stop
    apart, against the rig's true f^-1(z) = z^2.2 (both scaled to 1 at code 255).
    Bound: 0.03 of full scale, 3.5 code steps where the curve is steepest (2.2/255 per
    code at the top) -- the fits' smoothness prior and noise cost about one."""
    rig = NonlinearRig(seed=3)
    rng = np.random.default_rng(1)
    radiance = 10 ** rng.uniform(-3.5, 0, size=(120, 160))
    times = 0.9 * 2.0 ** np.arange(7) / 8
    bracket = [rig.to_codes(rig.capture(radiance, t)) for t in times]
    codes = np.arange(256) / 255
    truth = rig.camera.to_linear(codes)
    for method in ("debevec", "robertson"):
        recovered = recover_camera_response(bracket, times, method)
        error = np.abs(recovered.to_linear(codes) - truth)[5:251].max()
        print(f"\n{method}: max abs error {error:.4f} of full scale (codes 5..250)")
        assert error < 0.03, method
        assert recovered.to_linear(np.uint8(255)) == pytest.approx(1.0)
        merged = merge_bracket(bracket, times, recovered)
        good = radiance * times[-1] > 1e-2  # well exposed somewhere in the bracket
        assert np.median(np.abs(merged - radiance)[good] / radiance[good]) < 0.05


def test_colour_recovery_gives_one_curve_per_channel():
    rig = NonlinearRig(seed=4)
    rng = np.random.default_rng(2)
    radiance = 10 ** rng.uniform(-3.5, 0, size=(60, 80, 3))
    times = 0.9 * 2.0 ** np.arange(7) / 8
    bracket = [rig.to_codes(rig.capture(radiance, t)) for t in times]
    recovered = recover_camera_response(bracket, times, "debevec")
    assert recovered.table.shape == (256, 3)
    truth = (np.arange(256) / 255)[:, None] ** 2.2
    assert np.abs(recovered.table - truth)[5:251].max() < 0.03


def one_line(error: pytest.ExceptionInfo) -> str:
    text = str(error.value)
    assert "\n" not in text
    return text


@pytest.mark.parametrize("times, problem", [
    ([0.01, 0.1], "bracket of pattern 'gray_07': 3 images but 2 exposure times "
                  "(an exposure is missing)"),
    ([0.1, 0.01, 1.0], "bracket of pattern 'gray_07': exposures out of order: 1/100 s "
                       "(image 2) after 1/10 s (image 1)"),
    ([0.1, 0.1, 1.0], "bracket of pattern 'gray_07': exposures out of order: 1/10 s "
                      "(image 2) the same as 1/10 s"),
    ([0.0, 0.1, 1.0], "bracket of pattern 'gray_07': exposure times must be positive"),
])
def test_bad_brackets_are_refused_naming_the_pattern(times, problem):
    images = [np.zeros((4, 4), np.uint8)] * 3
    with pytest.raises(CalibrationError) as error:
        merge_bracket(images, times, CameraResponse("linear"), pattern="gray_07")
    assert one_line(error).startswith(problem)


def test_pixels_saturated_in_every_exposure_are_counted():
    images = [np.full((4, 5), 0.5), np.full((4, 5), 0.9)]
    images[0][:2, :3] = images[1][:2, :3] = 1.0
    with pytest.raises(CalibrationError) as error:
        merge_bracket(images, [0.001, 0.01], CameraResponse("linear"), pattern="white")
    assert one_line(error) == ("bracket of pattern 'white': 6 pixels saturated in every "
                               "exposure, the shortest (1/1000 s) too; add a shorter exposure")


def test_images_that_do_not_agree_are_refused():
    with pytest.raises(CalibrationError, match="image 2 is"):
        check_bracket([np.zeros((4, 4)), np.zeros((4, 5))], [1, 2])
    with pytest.raises(CalibrationError, match="no image"):
        check_bracket([], [])
    with pytest.raises(CalibrationError, match=r"\(H, W\) or \(H, W, 3\)"):
        check_bracket([np.zeros((4, 4, 2))], [1])
    with pytest.raises(CalibrationError, match="black 0.5 and saturation 0.4"):
        merge_bracket([np.zeros((2, 2))], [1], CameraResponse("linear"), black=0.5,
                      saturation=0.4)


def test_recovery_refuses_what_it_cannot_fit():
    dim = [np.full((8, 8), 100, np.uint8), np.full((8, 8), 200, np.uint8)]
    with pytest.raises(CalibrationError, match="brightest code is 200"):
        recover_camera_response(dim, [0.1, 0.2])
    with pytest.raises(CalibrationError, match="needs 8-bit captures"):
        recover_camera_response([d.astype(np.uint16) for d in dim], [0.1, 0.2])
    with pytest.raises(CalibrationError, match="unknown response recovery 'mitsunaga'"):
        recover_camera_response(dim, [0.1, 0.2], "mitsunaga")


def test_a_recovered_table_keeps_its_shape_when_the_fit_leaves_code_0_free():
    """Debevec's fit weighs code 0 by zero: with few samples it came back at 20x the
    top (measured on the simulated rig). A running maximum carried that across every
    code (T's error 0.79); the weighted isotonic fit pools it with the low codes only
    (the defaults, 200 samples and lambda 50, keep the fit from leaving it free)."""
    from bigT.calibration.hdr import _monotone

    truth = (np.arange(256) / 255.0) ** 2.2
    fitted = truth.copy()
    fitted[:4] = [20.8, 18.5, 16.6, 14.8]  # the free end, as OpenCV returned it
    fitted[100:103] = fitted[100:103][::-1]  # and a small dip a fit may leave
    table = _monotone(fitted[:, None])[:, 0]
    assert np.all(np.diff(table) >= 0) and table.min() >= 0
    # the free end pooled with the codes up to where the curve reaches its mean (~0.09,
    # as measured on the rig), the curve above that untouched
    assert np.abs(table - truth).max() < 0.1
    np.testing.assert_allclose(table[110:], truth[110:], rtol=1e-12)
    assert np.abs(np.maximum.accumulate(fitted) - truth).max() > 1  # the old way
