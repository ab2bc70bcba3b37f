"""Synthetic projector-camera scenes with known ground truth (paper §5-6).

``bigT.scenes.<name>(size=(H, W), path=..., ...)`` builds a scene and returns a
:class:`Scene`; names: ``dihedral4`` (paper eq. 34), ``corner``, ``convex``, ``flat``,
``cornell``, ``hemispheres``. :func:`load` reopens one.

Modules: :mod:`.builder` (the resumable build), :mod:`.scene` (the reader),
:mod:`.ground_truth` (its layout on disk), :mod:`.preview`, :mod:`.paper_example`
(the paper's 4x4 dihedral); :mod:`.geometry`, :mod:`.radiosity` and :mod:`.stored` compute,
:mod:`.statistics` measures the ground truth's radii and bounce shares;
colour scenes (``colour=True``) add :mod:`.rig` (the projector's primaries and the
camera's sensitivities), :mod:`.colouring` (the rig applied to the pixels) and
:mod:`.palette` (the surfaces' RGB albedo).
Each is imported on first use of one of its names, so that listing the scenes
(:mod:`bigT.scenes.catalog`) stays cheap (no scipy.spatial, no zarr).
"""

from __future__ import annotations

import importlib

from .catalog import DEFAULT_SIZES, DENSITIES, SCENE_NAMES  # noqa: F401

#: Public name -> the module defining it, imported on first use.
_LAZY = {"Scene": "scene", "load": "scene", "exact_inverse_rows": "scene",
         "ColourRig": "rig",
         "dihedral4": "paper_example",
         **{name: "builder" for name in ("build", "convex", "corner", "cornell", "flat",
                                          "hemispheres", "make")}}
_SUBMODULES = ("builder", "catalog", "colouring", "geometry", "ground_truth", "palette",
               "paper_example", "preview", "radiosity", "rig", "scene", "statistics", "stored")

__all__ = ["DEFAULT_SIZES", "DENSITIES", "SCENE_NAMES", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    if name in _SUBMODULES:
        return importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'bigT.scenes' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_LAZY) + list(_SUBMODULES))
