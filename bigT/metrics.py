"""What a user reads of a compensated image: how close what the camera sees is to what
was desired, in the measures papers and people use.

Beside bigT's relative error ``||seen - desired|| / ||desired||``:

* **PSNR** (dB), ``10 log10(1 / mean((seen - desired)**2))``, and **SSIM** (Wang et al.
  2004), both on the values as given, with a data range of 1;
* **CIEDE2000 ΔE** (Sharma et al. 2005), per pixel between the two images in CIELAB
  (D65), its mean and 95th percentile. About 1 is the smallest difference an observer
  sees side by side; above 5, two colours look different at a glance.

They come from scikit-image (``peak_signal_noise_ratio``, ``structural_similarity``,
``rgb2lab``, ``deltaE_ciede2000``), not written here. ``rgb2lab`` expects sRGB-encoded
values: images in linear light (bigT's compensation works in linear light) are encoded
with :func:`bigT.colour.encode` first.

Grey images: ΔE is that of the grey replicated to R = G = B (a neutral colour whose
CIELAB lightness carries the whole difference), so grey and colour results read alike.

Images layer: numpy, scikit-image and :mod:`bigT.colour`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import colour
from .errors import ImageError

#: SSIM's window side (scikit-image's default); smaller for images under 7 pixels.
SSIM_WINDOW = 7
#: The ΔE percentile reported beside the mean.
DELTA_E_PERCENTILE = 95


@dataclass(frozen=True)
class ColourMetrics:
    """How close a seen image (or batch of them) is to the desired one.

    Attributes
    ----------
    relative_error : float
        ||seen - desired|| / ||desired|| over every value (nan when desired is 0).
    psnr_db : float
        Peak signal-to-noise ratio in dB, data range 1 (inf for identical images).
    ssim : float or None
        Structural similarity in [-1, 1], mean over the frames (None for images smaller
        than 3 x 3, where it has no window).
    delta_e_mean : float
        CIEDE2000 ΔE, mean over pixels.
    delta_e_p95 : float
        Its 95th percentile (:data:`DELTA_E_PERCENTILE`).
    """

    relative_error: float
    psnr_db: float
    ssim: float | None
    delta_e_mean: float
    delta_e_p95: float

    def describe(self) -> str:
        """One line: ``relative error 0.0123, PSNR 31.2 dB, SSIM 0.954, ΔE2000 mean 1.8
        / p95 4.1``."""
        ssim = "n/a" if self.ssim is None else f"{self.ssim:.3f}"
        return (f"relative error {self.relative_error:.4f}, PSNR {self.psnr_db:.1f} dB, "
                f"SSIM {ssim}, ΔE2000 mean {self.delta_e_mean:.2f} / "
                f"p{DELTA_E_PERCENTILE} {self.delta_e_p95:.2f}")


def image_metrics(seen: np.ndarray, desired: np.ndarray, *,
                  encoding_for_lab: str = "linear") -> ColourMetrics:
    """The :class:`ColourMetrics` of ``seen`` against ``desired``.

    Parameters
    ----------
    seen, desired : ndarray, the same shape
        One image, (H, W) grey or (H, W, 3) RGB, or a batch of them, (K, H, W) or
        (K, H, W, 3) (colour when the last axis is 3 and there are more than two axes).
    encoding_for_lab : one of :data:`bigT.colour.ENCODINGS`
        The encoding the values are in, which ΔE needs (CIELAB is of light as seen):
        ``"linear"`` (light, as compensation computes it) is sRGB-encoded before
        ``rgb2lab``; ``"srgb"`` values go as they are. PSNR, SSIM and the relative error
        are computed on the values as given.

    Returns
    -------
    ColourMetrics
    """
    seen, desired = _pair(seen, desired)
    frames_seen, frames_desired = _as_frames(seen), _as_frames(desired)
    delta_e = np.stack([delta_e_map(s, d, encoding=encoding_for_lab)
                        for s, d in zip(frames_seen, frames_desired)])
    return ColourMetrics(relative_error=_relative_error(seen, desired),
                         psnr_db=psnr(seen, desired),
                         ssim=_mean_ssim(frames_seen, frames_desired),
                         delta_e_mean=float(delta_e.mean()),
                         delta_e_p95=float(np.percentile(delta_e, DELTA_E_PERCENTILE)))


def delta_e_map(seen: np.ndarray, desired: np.ndarray, *, encoding: str = "linear") -> np.ndarray:
    """CIEDE2000 ΔE per pixel, for a picture of where the colours are off.

    Parameters
    ----------
    seen, desired : ndarray, shape (H, W, 3) (RGB) or (H, W) (grey, replicated to RGB)
    encoding : one of :data:`bigT.colour.ENCODINGS`, the values' (see
        :func:`image_metrics`).

    Returns
    -------
    ndarray, shape (H, W), float64, >= 0
    """
    # scikit-image: ~0.3 s to import, only when metrics are asked for
    from skimage.color import deltaE_ciede2000, rgb2lab

    seen, desired = _pair(seen, desired)
    if seen.ndim not in (2, 3) or (seen.ndim == 3 and seen.shape[2] != 3):
        raise ImageError(f"delta_e_map takes one (H, W) or (H, W, 3) image, got shape "
                         f"{seen.shape}")
    lab_seen = rgb2lab(_srgb_rgb(seen, encoding))
    lab_desired = rgb2lab(_srgb_rgb(desired, encoding))
    return deltaE_ciede2000(lab_desired, lab_seen, channel_axis=-1)


def psnr(seen: np.ndarray, desired: np.ndarray) -> float:
    """Peak signal-to-noise ratio of ``seen`` against ``desired``, in dB, data range 1;
    inf when they are equal."""
    from skimage.metrics import peak_signal_noise_ratio  # scikit-image: ~0.3 s, see above

    seen, desired = _pair(seen, desired)
    if np.array_equal(seen, desired):
        return float("inf")  # scikit-image divides by the zero error
    return float(peak_signal_noise_ratio(desired, seen, data_range=1.0))


def _mean_ssim(frames_seen: np.ndarray, frames_desired: np.ndarray) -> float | None:
    """SSIM averaged over frames ((K, H, W) or (K, H, W, 3)), the channels of a colour
    frame averaged by scikit-image; None when a frame is under 3 x 3."""
    from skimage.metrics import structural_similarity  # scikit-image: ~0.3 s, see above

    side = min(frames_seen.shape[1:3])
    window = min(SSIM_WINDOW, side if side % 2 else side - 1)
    if window < 3:
        return None
    colour_axis = -1 if frames_seen.ndim == 4 else None
    return float(np.mean([
        structural_similarity(d, s, data_range=1.0, win_size=window, channel_axis=colour_axis)
        for s, d in zip(frames_seen, frames_desired)]))


def _relative_error(seen: np.ndarray, desired: np.ndarray) -> float:
    den = np.linalg.norm(desired)
    return float(np.linalg.norm(seen - desired) / den) if den > 0 else float("nan")


def _pair(seen, desired) -> tuple[np.ndarray, np.ndarray]:
    seen = np.asarray(seen, dtype=np.float64)
    desired = np.asarray(desired, dtype=np.float64)
    if seen.shape != desired.shape:
        raise ImageError(f"the seen image's shape {seen.shape} differs from the desired "
                         f"image's {desired.shape}")
    return seen, desired


def _as_frames(images: np.ndarray) -> np.ndarray:
    """A batch of frames: (K, H, W) or (K, H, W, 3), from one image or a batch."""
    single = images.ndim == 2 or (images.ndim == 3 and images.shape[2] == 3)
    return images[None] if single else images


def _srgb_rgb(image: np.ndarray, encoding: str) -> np.ndarray:
    """(H, W, 3) sRGB-encoded values, what ``rgb2lab`` takes: a grey image replicated
    to three channels, linear light encoded."""
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    return colour.encode(image, "srgb") if colour.check_encoding(encoding) == "linear" else image
