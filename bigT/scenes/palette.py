"""The surfaces' colours of a colour scene: an RGB albedo per surface (face).

The Cornell box has its red left wall and green right wall (the colour bleeding of the
classic scene: the white back wall turns pink near the red one); the concave corner has
an orange left wall and a blue right one. Every other surface is white: the same albedo
in the three bands, the scene's grey ``albedo``.
"""

from __future__ import annotations

import numpy as np

from ..errors import InvalidMatrixError, ShapeMismatchError

#: RGB albedo per face of the scenes that have coloured surfaces (faces as numbered by
#: :mod:`.geometry`: cornell 0 back, 1 left, 2 right, 3 top, 4 bottom; corner 0 left,
#: 1 right). Faces not listed are white.
PALETTES = {
    "cornell": {1: (0.63, 0.07, 0.05), 2: (0.12, 0.48, 0.08)},
    "corner": {0: (0.75, 0.38, 0.08), 1: (0.08, 0.22, 0.70)},
}


def surface_albedo(name: str, n_faces: int, white: float) -> np.ndarray:
    """(n_faces, 3) RGB albedo of each face of scene ``name``: its palette's colours,
    ``white`` in every band elsewhere."""
    table = np.full((n_faces, 3), float(white))
    for face, rgb in PALETTES.get(name, {}).items():
        if face < n_faces:
            table[face] = rgb
    return table


def band_albedo(name: str, albedo, size, faces: np.ndarray, pixel_perm: np.ndarray
                ) -> tuple[np.ndarray, object, list | None]:
    """The (n, 3) albedo of each pixel's patch in the bands R, G, B, in the store's
    pixel order, its label for the summary, and the per-face table (None for a texture).

    Parameters
    ----------
    name : str
        The scene (its palette, :data:`PALETTES`).
    albedo : float or ndarray (H, W, 3)
        The white surfaces' albedo (the palette colours the others), or an RGB texture
        (row-major image) that replaces the palette.
    size : (H, W)
    faces : ndarray, (n,) int
        The face of each pixel, in the store's pixel order.
    pixel_perm : ndarray, (n,) int64
        The pixel order's permutation (stored pixel -> row-major pixel).
    """
    H, W = size
    a = np.asarray(albedo, dtype=np.float64)
    if a.ndim == 0:
        table = surface_albedo(name, int(faces.max()) + 1 if len(faces) else 1, float(a))
        bands, label, record = table[faces], float(a), table.tolist()
    elif a.shape == (H, W, 3):
        bands, label, record = a.reshape(H * W, 3)[pixel_perm], "texture", None
    else:
        raise ShapeMismatchError(f"the albedo of a colour scene must be a number (its white "
                                 f"surfaces) or an (H, W, 3) = {(H, W, 3)} RGB texture, got "
                                 f"shape {a.shape}")
    if not np.isfinite(bands).all() or (bands <= 0).any() or (bands >= 1).any():
        raise InvalidMatrixError("albedo must lie in (0, 1) in every band: a black surface (0) "
                                 "sends no light back and makes T singular, one reflecting all "
                                 "light (1) makes the bounce series diverge")
    return bands, label, record
