"""Synthetic projector-camera scenes with known ground truth (paper §5-6).

``bigT.scenes.<name>(size=(H, W), path=..., ...)`` builds a scene and returns a
:class:`Scene`; names: ``dihedral4`` (paper eq. 34), ``corner``, ``convex``, ``flat``,
``cornell``, ``hemispheres``. :func:`load` reopens one. See :mod:`bigT.scenes.builder`.
"""

from .builder import (  # noqa: F401
    DENSITIES,
    SCENE_NAMES,
    Scene,
    build,
    convex,
    corner,
    cornell,
    dihedral4,
    exact_inverse_rows,
    flat,
    hemispheres,
    load,
    make,
)
