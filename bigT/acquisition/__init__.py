"""From a projector-camera rig's captures to T (paper §2.2, §6.1-6.1.1, §6.3).

``patterns`` -> project and capture -> ``build`` (correspondence, T tile row by tile
row) -> ``validate`` (T 1 against the white capture, paper Fig. 8). ``simulate`` stands
in for the rig: it renders the captures from a synthetic scene.

Each name is imported from its module on first use, so that writing patterns (numpy and
images) does not import what building T needs (the stores: zarr, scipy; ~0.5 s).
"""

from __future__ import annotations

import importlib

#: Public name -> the module defining it, imported on first use.
_LAZY = {
    **dict.fromkeys(("BuildReport", "BuildSettings", "build_transport",
                     "load_camera_response", "load_correspondence"), "build"),
    "Captures": "captures",
    "Correspondence": "correspondence",
    **dict.fromkeys(("METHODS", "PRIMARIES", "Manifest", "Pattern", "make_manifest",
                     "read_manifest"), "manifest"),
    **dict.fromkeys(("Mixing", "read_mixing"), "mixing"),
    **dict.fromkeys(("decode_graycode", "pattern_image", "write_patterns"), "patterns"),
    **dict.fromkeys(("CameraModel", "read_camera_model", "simulate_captures"), "simulate"),
}

__all__ = list(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module 'bigT.acquisition' has no attribute {name!r}")


def __dir__():
    return sorted(list(globals()) + list(_LAZY))
