"""bigT.calibration: the radiometry of a real rig (docs/CALIBRATION.md).

A projector's response, fitted from a ramp and inverted to encode linear light into the
integers it is sent (:mod:`.response`, dithering in :mod:`.dither`); a camera's response,
known (linear, sRGB, gamma) or recovered from exposure brackets, and the merge of a
bracket into linear radiance (:mod:`.camera`, :mod:`.hdr`); RAW captures and EXIF
exposure times (:mod:`.raw`); and a simulated nonlinear rig (:mod:`.rig`).

Below storage in the layers: numpy and scipy only at import; OpenCV, rawpy, Pillow and
matplotlib are imported by the functions that need them.
"""

from .camera import CameraResponse, normalised_codes, parse_camera_response
from .hdr import check_bracket, merge_bracket, recover_camera_response
from .raw import exposure_time_from_exif, read_raw
from .response import (Clipping, ProjectorResponse, fit_projector_response,
                       load_projector_response)
from .rig import NonlinearRig

__all__ = [
    "CameraResponse",
    "Clipping",
    "NonlinearRig",
    "ProjectorResponse",
    "check_bracket",
    "exposure_time_from_exif",
    "fit_projector_response",
    "load_projector_response",
    "merge_bracket",
    "normalised_codes",
    "parse_camera_response",
    "read_raw",
    "recover_camera_response",
]
