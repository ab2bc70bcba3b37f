"""Exposure brackets: merged into linear radiance, and the camera response recovered
from them.

A *bracket* is K captures of one pattern at exposure times t_1 < ... < t_K. Its merge
(:func:`merge_bracket`) estimates the radiance E of each pixel (and channel) from the
samples x_k = f^-1(z_k) ~ E t_k that are neither saturated (z_k >= ``saturation``) nor
near black (z_k <= ``black``), weighted by their noise:

    E = sum_k w_k x_k / t_k / sum_k w_k,   w_k = t_k h(z_k),

so E = sum_k h_k x_k / sum_k h_k t_k. Why t_k: a sample's noise is dominated by photon
shot noise, var(x_k) ~ E t_k, so var(x_k / t_k) ~ E / t_k and the inverse-variance
weight is proportional to t_k -- the longer exposure wins where it is not saturated.
Why h, the hat h(z) = min(z - black, saturation - z) (0 outside (black, saturation)):
near either end the response is least certain (a recovered curve's ends rest on few
samples, the top on the sensor's soft roll-off), so those samples fade out rather than
switch off. A pixel with no sample inside (black, saturation) keeps the longest
exposure that is not saturated (a dark pixel, read as dark); one saturated in every
exposure is refused, counted, naming the pattern.

Response recovery (:func:`recover_camera_response`) is OpenCV's: Debevec and Malik
(SIGGRAPH 1997, a smooth least-squares fit of log f^-1) or Robertson et al. (2003, an
iterated maximum-likelihood fit), on 8-bit brackets.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..errors import CalibrationError
from .camera import CHANNEL_NAMES, CameraResponse, normalised_codes

#: Recovery methods of :func:`recover_camera_response`.
RECOVERY_METHODS = ("debevec", "robertson")
#: A bracket for response recovery must reach this 8-bit code somewhere: the recovered
#: curve is scaled at the top code, which must rest on data.
TOP_CODE_NEEDED = 250


def _who(pattern: str | None) -> str:
    return f"bracket of pattern {pattern!r}" if pattern is not None else "bracket"


def _seconds(t: float) -> str:
    return f"1/{1 / t:.4g} s" if t < 1 else f"{t:.4g} s"


def check_bracket(images: Sequence, exposure_times, pattern: str | None = None
                  ) -> tuple[list[np.ndarray], np.ndarray]:
    """Check an exposure bracket and return it as arrays.

    Parameters
    ----------
    images : sequence of K arrays, each (H, W) or (H, W, 3), one dtype
    exposure_times : sequence of K floats, seconds, strictly increasing
    pattern : str, optional, the pattern the bracket captured (named in errors)

    Returns
    -------
    images : list of K ndarrays
    times : ndarray, shape (K,), float64

    Raises
    ------
    CalibrationError
        No image, a missing exposure (counts that differ), times not positive or not
        strictly increasing ("out of order"), images of different shapes or types; one
        line naming the pattern.
    """
    who = _who(pattern)
    images = [np.asarray(image) for image in images]
    times = np.asarray(exposure_times, dtype=np.float64).ravel()
    if not images:
        raise CalibrationError(f"{who}: no image")
    if len(images) != times.size:
        raise CalibrationError(f"{who}: {len(images)} images but {times.size} exposure times "
                               "(an exposure is missing)")
    if not (np.isfinite(times).all() and (times > 0).all()):
        raise CalibrationError(f"{who}: exposure times must be positive seconds, not "
                               f"{times.tolist()}")
    for k in range(1, times.size):
        if times[k] <= times[k - 1]:
            same = "the same as" if times[k] == times[k - 1] else "after"
            raise CalibrationError(
                f"{who}: exposures out of order: {_seconds(times[k])} (image {k + 1}) "
                f"{same} {_seconds(times[k - 1])} (image {k}); they must increase strictly")
    first = images[0]
    if first.ndim not in (2, 3) or (first.ndim == 3 and first.shape[2] not in CHANNEL_NAMES):
        raise CalibrationError(f"{who}: an image of shape {first.shape}: (H, W) or (H, W, 3)")
    for k, image in enumerate(images[1:], start=2):
        if image.shape != first.shape or image.dtype != first.dtype:
            raise CalibrationError(f"{who}: image {k} is {image.shape} {image.dtype}, image 1 "
                                   f"{first.shape} {first.dtype}")
    return images, times


def hat_weight(z: np.ndarray, saturation: float, black: float) -> np.ndarray:
    """h(z) = min(z - black, saturation - z), 0 outside (black, saturation)."""
    return np.clip(np.minimum(z - black, saturation - z), 0.0, None)


def merge_bracket(images: Sequence, exposure_times, response: CameraResponse, *,
                  saturation: float = 0.98, black: float = 0.02,
                  pattern: str | None = None) -> np.ndarray:
    """Merge an exposure bracket into linear radiance (module docstring).

    Parameters
    ----------
    images : sequence of K arrays, each (H, W) or (H, W, C)
        The captures, shortest exposure first: unsigned integer codes or normalised
        floats (:func:`bigT.calibration.camera.normalised_codes`).
    exposure_times : sequence of K floats, seconds, strictly increasing
    response : CameraResponse, the camera's linearisation
    saturation : float, a sample at or above this normalised code is saturated
    black : float, a sample at or below this normalised code is near black
    pattern : str, optional, named in errors

    Returns
    -------
    ndarray of float64, shape (H, W) or (H, W, C)
        Radiance: linear signal per second of exposure.

    Raises
    ------
    CalibrationError
        A bad bracket (:func:`check_bracket`), thresholds out of order, a pixel
        saturated in every exposure (counted).
    """
    images, times = check_bracket(images, exposure_times, pattern)
    if not 0.0 <= black < saturation <= 1.0:
        raise CalibrationError(f"{_who(pattern)}: thresholds black {black:g} and saturation "
                               f"{saturation:g} must satisfy 0 <= black < saturation <= 1")
    signal = np.zeros(images[0].shape)
    exposure = np.zeros(images[0].shape)   # sum_k h_k t_k
    fallback = np.full(images[0].shape, np.nan)  # the longest unsaturated exposure's x / t
    for image, t in zip(images, times):
        z = normalised_codes(image)
        x = response.to_linear(image)
        h = hat_weight(z, saturation, black)
        signal += h * x
        exposure += h * t
        fallback = np.where(z < saturation, x / t, fallback)
    saturated = np.isnan(fallback)
    if saturated.any():
        pixels = int(np.count_nonzero(saturated if saturated.ndim == 2 else saturated.any(-1)))
        raise CalibrationError(
            f"{_who(pattern)}: {pixels} pixels saturated in every exposure, the shortest "
            f"({_seconds(times[0])}) too; add a shorter exposure")
    return np.where(exposure > 0, signal / np.where(exposure > 0, exposure, 1.0), fallback)


def recover_camera_response(images: Sequence, exposure_times, method: str = "debevec", *,
                            samples: int = 200, smoothness: float = 50.0,
                            pattern: str | None = None) -> CameraResponse:
    """The camera's response recovered from an 8-bit exposure bracket (OpenCV's photo
    module: ``cv2.createCalibrateDebevec`` or ``cv2.createCalibrateRobertson``).

    Parameters
    ----------
    images : sequence of K uint8 arrays, (H, W) or (H, W, 3)
        A bracket of a scene with a wide range of radiances (every code should be
        reached by some pixel in some exposure), shortest exposure first.
    exposure_times : sequence of K floats, seconds, strictly increasing
    method : ``"debevec"`` or ``"robertson"``
    samples : int, pixel locations Debevec's fit uses (on a grid)
    smoothness : float, Debevec's smoothness weight (lambda)

        OpenCV's defaults (70 samples, lambda 10) leave the codes few samples reach
        free: on the simulated rig's brackets (benchmarks/bench_calibration.py, 3 and 4
        exposures 8x apart) the fitted curve rose to 20-300x its top at code 0 in 3 of 4
        cases, and T's error was 0.13 (3 exposures) and 0.79 (4); 200 samples and lambda
        50 kept it within 0.012-0.027 of the true gamma-2.2 curve in all four.
    pattern : str, optional, named in errors

    Returns
    -------
    CameraResponse
        A ``table`` of 256 codes x C channels (1 for grey): codes no sample reached
        interpolated, codes above :data:`TOP_CODE_NEEDED` (saturated) extrapolated
        from those below, made non-decreasing and scaled to 1 at code 255 (the methods
        fix the scale only up to a constant).
    """
    images, times = check_bracket(images, exposure_times, pattern)
    if method not in RECOVERY_METHODS:
        raise CalibrationError(f"unknown response recovery {method!r} "
                               f"(use {', '.join(RECOVERY_METHODS)})")
    if images[0].dtype != np.uint8:
        raise CalibrationError(f"{_who(pattern)}: response recovery needs 8-bit captures, "
                               f"not {images[0].dtype}")
    brightest = int(max(int(image.max()) for image in images))
    if brightest < TOP_CODE_NEEDED:
        raise CalibrationError(
            f"{_who(pattern)}: its brightest code is {brightest}, so the response above it "
            f"would be a guess; add a longer exposure (some pixels should reach "
            f"{TOP_CODE_NEEDED} or more)")
    import cv2  # OpenCV: ~0.1 s and a large library, only when a response is recovered

    grey = images[0].ndim == 2
    # OpenCV 5.0's Robertson crashes on one-channel images: grey goes in as 3 equal ones
    frames = [np.ascontiguousarray(np.repeat(i[..., None], 3, axis=2) if grey else i)
              for i in images]
    calibrate = (cv2.createCalibrateDebevec(samples=samples, lambda_=smoothness)
                 if method == "debevec" else cv2.createCalibrateRobertson())
    table = np.asarray(calibrate.process(frames, times.astype(np.float32)),
                       dtype=np.float64).reshape(256, 3)
    table = _monotone(_extrapolate_top(_fill_unseen(table[:, :1] if grey else table)))
    return CameraResponse("table", table=table / table[-1], source=f"recovered ({method})")


def _monotone(table: np.ndarray) -> np.ndarray:
    """The fitted table made non-decreasing and non-negative by isotonic regression,
    each code weighted as the fits weigh it (the hat, least at codes 0 and 255): a
    running maximum instead carried a code the fit left unconstrained (code 0 at 20x
    the top, measured) across every code above it, where this pools it with the low
    codes only (to ~0.09 of the top on the rig; the defaults above keep it bound)."""
    from scipy.optimize import isotonic_regression  # scipy.optimize: ~0.2 s, here only

    codes = np.arange(table.shape[0])
    weights = np.minimum(codes, codes[-1] - codes) + 1.0
    return np.stack([isotonic_regression(np.maximum(table[:, c], 0.0), weights=weights).x
                     for c in range(table.shape[1])], axis=1)


def _fill_unseen(table: np.ndarray) -> np.ndarray:
    """Codes no sample reached come back NaN from Robertson's fit: interpolated
    between their seen neighbours (held at the ends)."""
    codes = np.arange(table.shape[0])
    filled = table.copy()
    for c in range(table.shape[1]):
        seen = np.isfinite(table[:, c])
        if not seen.any():
            raise CalibrationError("response recovery failed: no code was reached")
        filled[:, c] = np.interp(codes, codes[seen], table[seen, c])
    return filled


def _extrapolate_top(table: np.ndarray) -> np.ndarray:
    """The codes above :data:`TOP_CODE_NEEDED` are saturated samples, which both fits
    weigh (almost) zero: Robertson's estimate there averages whatever saturated, often
    twice the true value. Replaced by the straight line through codes 240 .. 250."""
    fit = np.arange(TOP_CODE_NEEDED - 10, TOP_CODE_NEEDED + 1)
    top = np.arange(TOP_CODE_NEEDED + 1, table.shape[0])
    out = table.copy()
    for c in range(table.shape[1]):
        slope, intercept = np.polyfit(fit, table[fit, c], 1)
        out[top, c] = intercept + slope * top
    return out
