"""The colour rig of a synthetic scene: projector primaries and camera sensitivities.

A colour scene transports light in three spectral *bands* k (R, G, B). The projector's
primary j lights band k with weight ``P[k, j]``; the camera's channel i sees band k with
weight ``C[i, k]``. A band's light travels the scene exactly as grey light does, with the
band's albedo, so with T_k the grey transport of band k::

    T[3 p + i, 3 q + j] = sum_k C_p[i, k] T_k[p, q] P_q[k, j]

(camera pixel p, projector pixel q). Without per-pixel variation, C_p = C and P_q = P
for every pixel: the mixing is *global*, T = (I (x) C) blockdiag(T_R, T_G, T_B)
(I (x) P) with the bands interleaved (index 3 p + k). With variation each pixel's C_p
and P_q differ from C and P by a few percent (seeded), as a real camera's vignetting
and a projector's colour non-uniformity do, and T has no such factorisation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import BigTError

#: The colour mixings a scene may have: one 3x3 pair for the whole rig, or per pixel.
MIXINGS = ("global", "per-pixel")

#: Camera sensitivities (channel i, row, to band k, column): realistic cross-talk, the
#: green channel seeing the most of its neighbours, rows not summing to the same.
DEFAULT_CAMERA = ((0.90, 0.15, 0.05),
                  (0.12, 0.85, 0.10),
                  (0.05, 0.20, 0.80))
#: Projector primaries (band k, row, lit by primary j, column).
DEFAULT_PROJECTOR = ((0.92, 0.10, 0.05),
                     (0.08, 0.88, 0.12),
                     (0.05, 0.07, 0.95))
#: Relative amplitude of the per-pixel variation of ``--mixing per-pixel`` (3 %).
DEFAULT_VARIATION = 0.03


def _matrix3(value, name: str) -> tuple[tuple[float, ...], ...]:
    m = np.asarray(value, dtype=np.float64)
    if m.shape != (3, 3) or not np.isfinite(m).all() or (m < 0).any():
        raise BigTError(f"{name} must be a 3x3 matrix of finite numbers >= 0, got {value!r:.80}")
    if np.linalg.cond(m) > 1e6:
        raise BigTError(f"{name} is singular (condition number {np.linalg.cond(m):.3g}): the "
                        "camera could not tell its channels apart")
    return tuple(tuple(float(v) for v in row) for row in m)


@dataclass(frozen=True)
class ColourRig:
    """A projector-camera rig's colour mixing.

    Attributes
    ----------
    camera : 3x3 tuple of float
        C[i][k]: camera channel i's response to band k.
    projector : 3x3 tuple of float
        P[k][j]: band k's response to projector primary j.
    variation : float
        Relative amplitude of the per-pixel variation: each entry of C_p and P_q is
        C[i][k] (1 + variation u) with u uniform in [-1, 1], drawn per pixel and entry
        (0: the mixing is global).
    seed : int
        Seeds the per-pixel variation.
    """

    camera: tuple = DEFAULT_CAMERA
    projector: tuple = DEFAULT_PROJECTOR
    variation: float = 0.0
    seed: int = 0

    def __post_init__(self):
        object.__setattr__(self, "camera", _matrix3(self.camera, "camera"))
        object.__setattr__(self, "projector", _matrix3(self.projector, "projector"))
        v = float(self.variation)
        if not 0.0 <= v < 0.5:
            raise BigTError(f"variation must lie in [0, 0.5), got {self.variation!r:.40}")
        object.__setattr__(self, "variation", v)
        object.__setattr__(self, "seed", int(self.seed))

    @classmethod
    def named(cls, mixing: str = "global", seed: int = 0) -> "ColourRig":
        """The default rig with a global mixing, or with ``DEFAULT_VARIATION`` per pixel."""
        if mixing not in MIXINGS:
            raise BigTError(f"mixing must be one of {MIXINGS}, got {mixing!r:.40}")
        return cls(variation=0.0 if mixing == "global" else DEFAULT_VARIATION, seed=seed)

    @property
    def mixing(self) -> str:
        """``"global"`` (one C and P for every pixel) or ``"per-pixel"``."""
        return "global" if self.variation == 0 else "per-pixel"

    @property
    def C(self) -> np.ndarray:
        """(3, 3) float64 camera sensitivities."""
        return np.array(self.camera)

    @property
    def P(self) -> np.ndarray:
        """(3, 3) float64 projector primaries."""
        return np.array(self.projector)

    def blocks(self, size) -> tuple[np.ndarray, np.ndarray]:
        """(C_p, P_q) of every pixel of an (H, W) image, each (H W, 3, 3) float64 in
        row-major pixel order (renumber with the pixel order's permutation)."""
        H, W = (int(s) for s in size)
        C = np.broadcast_to(self.C, (H * W, 3, 3)).copy()
        P = np.broadcast_to(self.P, (H * W, 3, 3)).copy()
        if self.variation:
            # drawn in row-major order so the rig does not depend on the store's order
            rng = np.random.default_rng([self.seed, 0x716])
            C *= 1.0 + self.variation * rng.uniform(-1.0, 1.0, C.shape)
            P *= 1.0 + self.variation * rng.uniform(-1.0, 1.0, P.shape)
        return C, P

    def record(self) -> dict:
        """The summary's record of the rig (flat keys: docs/FORMAT.md)."""
        return {"mixing": self.mixing, "rig_camera": [list(r) for r in self.camera],
                "rig_projector": [list(r) for r in self.projector],
                "rig_variation": self.variation, "rig_seed": self.seed}

    @classmethod
    def from_record(cls, summary: dict) -> "ColourRig":
        """The rig a scene's summary records (:meth:`record`)."""
        return cls(summary["rig_camera"], summary["rig_projector"],
                   summary["rig_variation"], summary["rig_seed"])

    def metadata(self) -> dict | None:
        """T's ``metadata["mixing"]`` when the mixing is global, else None."""
        if self.mixing != "global":
            return None
        return {"camera": [list(r) for r in self.camera],
                "projector": [list(r) for r in self.projector]}
