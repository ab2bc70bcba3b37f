"""A colour scene's rig applied to its pixels (:class:`ColourParts`): the camera's and
the projector's 3x3 blocks in the store's pixel order, the block-diagonal that mixes T's
rows, and the true first bounce's blocks; and the rig a build asks for."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..errors import BigTError
from . import radiosity
from .rig import ColourRig


@dataclass(frozen=True)
class ColourParts:
    """The rig of a colour scene applied to its pixels, in the store's pixel order.

    Attributes
    ----------
    rig : ColourRig
    camera, projector : ndarray, (n_pixels, 3, 3) float64
        C_p of each camera pixel, P_q of each projector pixel.
    projector_matrix : csr_array, (3 n_pixels, 3 n_pixels)
        The block-diagonal of the P_q (T's rows are mixed by it from the right).
    first_bounce : ndarray, (n_pixels, 3, 3) float64
        The true first bounce F_p = C_p diag(f_p) P_p (f_p the bands' albedo times the
        pixel's gain): the diagonal blocks of F.
    surface_albedo : list or None
        The RGB albedo of each face (None for a texture), for the summary.
    """

    rig: ColourRig
    camera: np.ndarray
    projector: np.ndarray
    projector_matrix: sp.csr_array
    first_bounce: np.ndarray
    surface_albedo: list | None

    @classmethod
    def of(cls, rig: ColourRig, size, perm: np.ndarray, f_bands: np.ndarray,
           surface_albedo) -> "ColourParts":
        """The parts of ``rig`` for an image of ``size`` numbered by ``perm`` (stored
        pixel -> row-major pixel), with the bands' first bounce ``f_bands`` (n, 3)."""
        C, P = rig.blocks(size)
        C, P = C[perm], P[perm]
        F = np.einsum("nik,nk,nkj->nij", C, f_bands, P)
        return cls(rig, C, P, radiosity.block_diagonal(P), F, surface_albedo)

    def record(self) -> dict:
        return {"channels": 3, **self.rig.record(), "surface_albedo": self.surface_albedo}


def resolve_rig(colour: bool, mixing: str, rig, seed: int) -> ColourRig | None:
    """The rig of a colour scene (None for grey): ``rig`` when given, else the default
    rig with a ``mixing`` of "global" or "per-pixel" (seeded by the scene's seed)."""
    if rig is not None:
        if not isinstance(rig, ColourRig):
            raise BigTError(f"rig must be a bigT.scenes.rig.ColourRig, got {type(rig).__name__}")
        return rig
    return ColourRig.named(mixing, seed) if colour else None
