"""From a projector-camera rig's captures to T (paper §2.2, §6.1-6.1.1, §6.3).

``patterns`` -> project and capture -> ``build`` (correspondence, T tile row by tile
row) -> ``validate`` (T 1 against the white capture, paper Fig. 8). ``simulate`` stands
in for the rig: it renders the captures from a synthetic scene.
"""

from .build import (BuildReport, BuildSettings, build_transport, load_camera_response,
                    load_correspondence)
from .captures import Captures
from .correspondence import Correspondence
from .manifest import METHODS, PRIMARIES, Manifest, Pattern, make_manifest, read_manifest
from .mixing import Mixing, read_mixing
from .patterns import decode_graycode, pattern_image, write_patterns
from .simulate import CameraModel, read_camera_model, simulate_captures

__all__ = [
    "BuildReport", "BuildSettings", "build_transport", "load_camera_response",
    "load_correspondence", "Captures",
    "Correspondence", "METHODS", "PRIMARIES", "Manifest", "Pattern", "make_manifest",
    "read_manifest", "Mixing", "read_mixing",
    "decode_graycode", "pattern_image", "write_patterns", "CameraModel", "read_camera_model",
    "simulate_captures",
]
