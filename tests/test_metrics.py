"""bigT.metrics (issue #28, point 6) against independent references: Sharma et al.'s
CIEDE2000 test pairs, CIELAB's white and mid grey by the CIE formulas, PSNR and the
relative error by hand, SSIM of constant images by its formula."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bigT import colour
from bigT.errors import ImageError
from bigT.metrics import ColourMetrics, delta_e_map, image_metrics, psnr

#: Pairs of Sharma, Wu and Dalal (2005), "The CIEDE2000 color-difference formula:
#: implementation notes, supplementary test data", table 1 (pairs 7, 17 and 25: those
#: inside the sRGB gamut), with their ΔE00 to 4 decimals.
SHARMA_PAIRS = [
    ((50.0, 0.0, 0.0), (50.0, -1.0, 2.0), 2.3669),
    ((50.0, 2.5, 0.0), (73.0, 25.0, -18.0), 27.1492),
    ((60.2574, -34.0099, 36.2677), (60.4626, -34.1751, 39.4387), 1.2644),
]


def _srgb_of_lab(lab) -> np.ndarray:
    from skimage.color import lab2rgb

    return lab2rgb(np.array(lab, float)[None, None])  # (1, 1, 3), sRGB-encoded


@pytest.mark.parametrize("lab1, lab2, expected", SHARMA_PAIRS)
def test_delta_e_of_sharmas_pairs_through_rgb(lab1, lab2, expected):
    """Each pair as sRGB pixels, then as linear light: the same ΔE00 either way."""
    rgb1, rgb2 = _srgb_of_lab(lab1), _srgb_of_lab(lab2)
    assert delta_e_map(rgb2, rgb1, encoding="srgb")[0, 0] == pytest.approx(expected, abs=1e-4)
    lin1, lin2 = colour.decode(rgb1, "srgb"), colour.decode(rgb2, "srgb")
    assert delta_e_map(lin2, lin1)[0, 0] == pytest.approx(expected, abs=1e-4)


def _lightness(Y: float) -> float:
    """CIE 1976 L* of relative luminance Y (white Y = 1)."""
    t = Y ** (1 / 3) if Y > (6 / 29) ** 3 else Y / (3 * (6 / 29) ** 2) + 4 / 29
    return 116 * t - 16


def _delta_e_of_neutrals(L1: float, L2: float) -> float:
    """CIEDE2000 between two neutral colours (a = b = 0): only the lightness term."""
    mean = (L1 + L2) / 2
    S_L = 1 + 0.015 * (mean - 50) ** 2 / math.sqrt(20 + (mean - 50) ** 2)
    return abs(L1 - L2) / S_L


def test_grey_delta_e_is_lightness_of_linear_light():
    """Linear 0.18 (mid grey) against white: L* 49.50 against 100, by the CIE formulas.
    Had the linear values gone to rgb2lab unencoded, L* would be 18.9."""
    seen, desired = np.full((4, 5), 0.18), np.ones((4, 5))
    expected = _delta_e_of_neutrals(_lightness(0.18), 100.0)
    np.testing.assert_allclose(delta_e_map(seen, desired), expected, rtol=1e-4)
    black = np.zeros((4, 5, 3))
    np.testing.assert_allclose(delta_e_map(black, np.ones((4, 5, 3))), 100.0, rtol=1e-6)
    m = image_metrics(seen, desired)
    assert m.delta_e_mean == pytest.approx(expected, rel=1e-4)
    assert m.delta_e_p95 == pytest.approx(expected, rel=1e-4)


def test_identical_images_are_perfect():
    img = np.random.default_rng(0).uniform(0, 1, (9, 11, 3))
    m = image_metrics(img, img.copy())
    assert m == ColourMetrics(0.0, math.inf, 1.0, 0.0, 0.0)
    assert psnr(img, img) == math.inf


def test_psnr_and_relative_error_by_hand():
    desired = np.full((8, 8), 0.5)
    seen = desired.copy()
    seen[0, :4] += 0.1   # 4 errors of 0.1
    seen[7, 7] -= 0.3    # and one of 0.3
    mse = (4 * 0.01 + 0.09) / 64
    assert psnr(seen, desired) == pytest.approx(10 * math.log10(1 / mse), rel=1e-12)
    m = image_metrics(seen, desired)
    assert m.psnr_db == pytest.approx(10 * math.log10(1 / mse), rel=1e-12)
    assert m.relative_error == pytest.approx(math.sqrt(0.13) / math.sqrt(64 * 0.25), rel=1e-12)


@pytest.mark.parametrize("shape", [(10, 12), (10, 12, 3)])
def test_ssim_of_constant_images_by_its_formula(shape):
    """Constant images have no variance: SSIM = (2 mx my + C1) / (mx^2 + my^2 + C1),
    C1 = (0.01 x data range)^2."""
    c1 = 0.01 ** 2
    m = image_metrics(np.full(shape, 0.4), np.full(shape, 0.5))
    assert m.ssim == pytest.approx((2 * 0.2 + c1) / (0.16 + 0.25 + c1), rel=1e-9)


def test_batches_pool_pixels_and_average_ssim():
    rng = np.random.default_rng(3)
    desired = rng.uniform(0.2, 0.8, (3, 10, 12, 3))
    seen = desired + rng.normal(0, 0.02, desired.shape)
    m = image_metrics(seen, desired)
    maps = np.stack([delta_e_map(s, d) for s, d in zip(seen, desired)])
    assert m.delta_e_mean == pytest.approx(maps.mean(), rel=1e-12)
    assert m.delta_e_p95 == pytest.approx(np.percentile(maps, 95), rel=1e-12)
    one = [image_metrics(s, d).ssim for s, d in zip(seen, desired)]
    assert m.ssim == pytest.approx(np.mean(one), rel=1e-12)
    assert 0 < m.ssim < 1 and m.delta_e_p95 > m.delta_e_mean > 0


def test_tiny_images_have_no_ssim_and_shapes_must_agree():
    assert image_metrics(np.zeros((2, 5)), np.ones((2, 5))).ssim is None
    with pytest.raises(ImageError, match=r"\(4, 5\) differs from the desired image's \(4, 6\)"):
        image_metrics(np.zeros((4, 5)), np.zeros((4, 6)))
    with pytest.raises(ImageError, match="unknown image encoding"):
        delta_e_map(np.zeros((4, 5)), np.zeros((4, 5)), encoding="rec709")


def test_describe_is_one_line():
    line = ColourMetrics(0.01234, 31.25, 0.9543, 1.84, 4.12).describe()
    assert line == "relative error 0.0123, PSNR 31.2 dB, SSIM 0.954, ΔE2000 mean 1.84 / p95 4.12"
