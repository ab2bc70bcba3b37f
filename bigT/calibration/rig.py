"""A nonlinear projector-camera rig, for simulation: what a real rig does to light that
the linear model of ``acquire simulate`` leaves out.

Projector (per channel when its parameters are given per channel), value v in [0, 1]:

    r(v) = b + (1 - b) s(v^gamma),   s(u) = u + sigma u (1 - u)

with b the black level (light leaked at 0), gamma the display gamma and sigma in
[0, 1) the *shoulder*: s(1) = 1, its slope falls from 1 + sigma at 0 to 1 - sigma at 1,
so the top end rolls off softly as a lamp's and a DLP's do. r(1) = 1.

Camera, radiance E (linear light per second, in units where 1 fills the sensor in one
second) and exposure t seconds: the sensor collects s = E t of its full well, with
photon shot noise (a Poisson count of ``full_well_electrons`` s electrons, drawn as its
Gaussian approximation), clips at the full well (1), adds read noise (Gaussian, in full
well units), then the camera applies its response (z = f(s), :meth:`CameraResponse.encode`)
and quantises to ``bits`` bits. The noise is seeded by (``seed``, ``frame``, t): the
same call gives the same image, two exposures or frames independent noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import CalibrationError
from .camera import CameraResponse


def _default_camera() -> CameraResponse:
    return CameraResponse("gamma", gamma=2.2)


@dataclass(frozen=True, eq=False)
class NonlinearRig:
    """A simulated projector and camera with realistic nonlinearities (module docstring).

    Attributes
    ----------
    projector_gamma : float or tuple of 3 floats, gamma of r(v) (per channel if 3)
    projector_black : float or tuple of 3 floats, b = r(0), in [0, 1)
    projector_shoulder : float or tuple of 3 floats, sigma in [0, 1)
    camera : CameraResponse, the camera's response (default gamma 2.2)
    full_well_electrons : float, electrons at full well (shot noise; inf: none)
    read_noise : float, standard deviation of the read noise, in full-well units
    bits : int, the camera's bit depth (8 or 16)
    seed : int
    """

    projector_gamma: float | tuple[float, ...] = 2.2
    projector_black: float | tuple[float, ...] = 0.02
    projector_shoulder: float | tuple[float, ...] = 0.3
    camera: CameraResponse = field(default_factory=_default_camera)
    full_well_electrons: float = 20000.0
    read_noise: float = 0.001
    bits: int = 8
    seed: int = 0

    def __post_init__(self):
        gamma, black, shoulder = self._projector_parameters()
        if not (np.all(gamma > 0) and np.all((0 <= black) & (black < 1))
                and np.all((0 <= shoulder) & (shoulder < 1))):
            raise CalibrationError("a rig's projector needs gamma > 0, black in [0, 1) and "
                                   "shoulder in [0, 1)")
        if self.bits not in (8, 16):
            raise CalibrationError(f"a rig's camera has 8 or 16 bits, not {self.bits!r}")
        if not (self.full_well_electrons > 0 and self.read_noise >= 0):
            raise CalibrationError("a rig's camera needs full_well_electrons > 0 and "
                                   "read_noise >= 0")

    def _projector_parameters(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return tuple(np.asarray(p, dtype=np.float64) for p in
                     (self.projector_gamma, self.projector_black, self.projector_shoulder))

    def project(self, values) -> np.ndarray:
        """r(v): the linear light the projector emits for ``values``.

        Parameters
        ----------
        values : array_like, any shape; (..., 3) when the parameters are per channel
            Projector values, clipped to [0, 1].

        Returns
        -------
        ndarray of float64, the shape of ``values``; 1 at full scale
        """
        gamma, black, shoulder = self._projector_parameters()
        u = np.clip(np.asarray(values, dtype=np.float64), 0.0, 1.0) ** gamma
        return black + (1.0 - black) * (u + shoulder * u * (1.0 - u))

    def capture(self, radiance, exposure: float, *, frame: int = 0) -> np.ndarray:
        """What the camera stores for ``radiance`` over ``exposure`` seconds.

        Parameters
        ----------
        radiance : array_like, (H, W) or (H, W, C), linear light per second (1 fills
            the full well in one second)
        exposure : float, seconds
        frame : int, tells apart the noise of captures at the same exposure

        Returns
        -------
        ndarray of float64, the shape of ``radiance``
            Normalised codes k / (2^bits - 1), integer k: the camera's quantised output.
        """
        radiance = np.asarray(radiance, dtype=np.float64)
        rng = np.random.default_rng(
            [self.seed, frame, int(np.float64(exposure).view(np.uint64))])
        collected = np.clip(radiance * exposure, 0.0, None)
        if np.isfinite(self.full_well_electrons):
            collected = collected + rng.standard_normal(radiance.shape) * np.sqrt(
                collected / self.full_well_electrons)
        signal = np.clip(collected, 0.0, 1.0) + self.read_noise * rng.standard_normal(
            radiance.shape)
        top = (1 << self.bits) - 1
        return np.rint(self.camera.encode(np.clip(signal, 0.0, 1.0)) * top) / top

    def to_codes(self, image) -> np.ndarray:
        """A :meth:`capture` as the camera's integers: uint8 (8 bits) or uint16."""
        top = (1 << self.bits) - 1
        return np.rint(np.asarray(image) * top).astype(np.uint8 if self.bits == 8 else np.uint16)
