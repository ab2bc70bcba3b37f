"""Synthetic projector-camera scenes with known ground truth (paper §5-6).

``bigT.scenes.<name>(size=(H, W), path=..., ...)`` builds a scene and returns a
:class:`Scene`; names: ``dihedral4`` (paper eq. 34), ``corner``, ``convex``, ``flat``,
``cornell``, ``hemispheres``. :func:`load` reopens one. See :mod:`bigT.scenes.builder`.

The builder is imported on first use of one of its names, so that listing the scenes
(:mod:`bigT.scenes.catalog`) stays cheap.
"""

from __future__ import annotations

import importlib

from .catalog import DEFAULT_SIZES, DENSITIES, SCENE_NAMES  # noqa: F401

_FROM_BUILDER = ("Scene", "build", "convex", "corner", "cornell", "dihedral4",
                 "exact_inverse_rows", "flat", "hemispheres", "load", "make")
_SUBMODULES = ("builder", "catalog", "geometry", "radiosity")

__all__ = ["DEFAULT_SIZES", "DENSITIES", "SCENE_NAMES", *_FROM_BUILDER]


def __getattr__(name: str):
    if name in _FROM_BUILDER:
        return getattr(importlib.import_module(".builder", __name__), name)
    if name in _SUBMODULES:
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'bigT.scenes' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_FROM_BUILDER) + list(_SUBMODULES))
