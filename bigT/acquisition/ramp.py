"""The projector's response, fitted from the captures of the pattern set's ramp.

The ramp (``ramp`` patterns, :mod:`.manifest`) is L uniform frames at levels 0 .. 1,
once per primary for colour. For each, the mean of its linear signal (the camera's
response undone, brackets merged, the black level subtracted) is taken over the camera
pixels the correspondence assigns to a projector super-pixel -- the pixels the
projector lights directly -- less those at full scale in the white capture:

* every pixel's signal is proportional to the projector's light r(v) (light transport
  is linear), so any set of pixels gives the curve's shape; the directly lit ones carry
  the most light, so their mean is the best measured. Pixels outside the projected area
  see only stray and interreflected light, a few per cent of it: they would add noise
  and no information;
* a pixel saturated in the white capture (single 8/16-bit exposures) is clipped at the
  top of the ramp and would bend the curve's shoulder down: left out (the ramp's
  frames are no brighter than white, so it is unclipped in all of them);
* colour: primary j's frames are read through the grey view (the mean of the camera's
  channels): every camera channel sees primary j's light in proportion to r_j(v),
  and their mean is better measured than any one of them.

The means are fitted by :func:`bigT.calibration.fit_projector_response` (isotonic
regression, then PCHIP; refused when not monotone or flat). With the black level the
build subtracts -- the black pattern's capture -- the ramp's level 0 is 0: the fitted
curve is the projector's light *above black*, in units of a full-scale pattern's, the
units of T (docs/CALIBRATION.md, T and the response). A ``--black`` frame that is the
camera's own dark level (lens capped) keeps the projector's black in the fit instead.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..calibration import ProjectorResponse, fit_projector_response
from ..calibration.response import DEFAULT_NOISE_FRACTION
from ..errors import AcquisitionError, CalibrationError
from .captures import Captures, grey_view
from .correspondence import Correspondence
from .manifest import Manifest

#: T's metadata key naming the response file kept in the store.
PROJECTOR_RESPONSE_KEY = "projector_response"
#: The response's file in the store directory (JSON, ``ProjectorResponse.save``).
PROJECTOR_RESPONSE_FILE = "projector_response.json"


def ramp_pixels(cap: Captures, corr: Correspondence) -> np.ndarray:
    """The camera pixels the ramp is averaged over (module docstring).

    Returns
    -------
    ndarray, shape (Hc, Wc), bool
    """
    return (corr.labels >= 0) & ~cap.saturated_mask(cap.manifest.single("white"))


def fit_ramp(manifest: Manifest, cap: Captures, corr: Correspondence) -> ProjectorResponse:
    """The projector's response from the ramp's captures, one curve per primary.

    Returns
    -------
    ProjectorResponse, levels (L,), output (L, C), C = 1 (grey) or 3 (R, G, B)

    Raises
    ------
    AcquisitionError
        No pixel to average over, or a ramp not monotone or flat (the library's one
        line, naming the captures folder).
    """
    pixels = ramp_pixels(cap, corr)
    count = int(pixels.sum())
    if count == 0:
        raise AcquisitionError("the projector ramp has no directly lit, unsaturated camera "
                               "pixel to be measured on", cap.folder)
    primaries = manifest.primaries()
    levels = np.array([p.level for p in manifest.ramp() if p.primary == primaries[0]])
    means = np.stack([[grey_view(cap.signal(p))[pixels].mean() for p in manifest.ramp()
                       if p.primary == j] for j in primaries], axis=1)
    # a mean of `count` signals, each holding its capture's noise and the black's; the
    # black capture does not see the noise that grows with the light (shot noise): the
    # library's default share of the span is the least assumed
    estimate = np.sqrt(2.0 / count) * cap.noise()
    noise = np.maximum(estimate, DEFAULT_NOISE_FRACTION * np.abs(means[-1] - means[0]))
    try:
        return fit_projector_response(levels, means, noise=noise[None, :])
    except CalibrationError as exc:
        raise AcquisitionError(f"projector ramp: {exc.template}", cap.folder) from None


def save_response(store: Path, response: ProjectorResponse) -> Path:
    """Keep ``response`` in the store directory (:data:`PROJECTOR_RESPONSE_FILE`)."""
    return response.save(Path(store) / PROJECTOR_RESPONSE_FILE)


def response_figure_path(store) -> Path:
    """``T-projector-response.png`` beside ``T.zarr``."""
    store = Path(store)
    name = store.name[:-5] if store.name.endswith(".zarr") else store.name
    return store.with_name(f"{name}-projector-response.png")
