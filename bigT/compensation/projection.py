"""What a compensation hands the projector: the rig's resolutions and its response
applied around the products with X.

:class:`Projection` is set up once per run from the stores and the options
(:func:`projection_for`):

* the rig's geometry (:mod:`.rig`), when T was acquired by ``bigT acquire build``: the
  desired images come at the camera's resolution (averaged onto the camera
  super-pixels T's rows are, through the stored correspondence) or at the
  super-pixels' own, and the projector's image goes out at its full resolution (each
  super-pixel's pixels its value, or ``smooth``: bilinear between their centres);
* the projector's response (:mod:`.projector`), when one is given or stored with T:
  the linear light is encoded through its inverse into the projector's 8- or 16-bit
  values; without one, linear light is written in the input's encoding, as before,
  and the header says so.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ImageError, Option
from ..images import declared_shape
from ..storage import as_store
from .encoding import FrameEncoding
from .projector import ProjectorEncoder, projector_encoder
from .rig import (RigGeometry, check_camera_or_grid, recorded_transport, rig_geometry,
                  stored_response_path)

#: The README section a user without a projector response is pointed to.
CALIBRATION_SECTION = "Calibrating a rig"


@dataclass(frozen=True)
class Projection:
    """The maps around a compensation's products.

    Attributes
    ----------
    geometry : RigGeometry or None, the rig's (None: T maps the images as they are)
    camera_input : bool, the desired images are the camera's (else the super-pixels')
    encoder : ProjectorEncoder or None, the projector's response (None: linear light)
    smooth : bool, bilinear super-pixels on the projector
    """

    geometry: RigGeometry | None = None
    camera_input: bool = False
    encoder: ProjectorEncoder | None = None
    smooth: bool = False

    def input_shape(self, grid) -> tuple[int, int] | None:
        """(H, W) the desired images must have."""
        if self.geometry is None:
            return grid
        return self.geometry.camera if self.camera_input else self.geometry.grid

    def output_shape(self, grid) -> tuple[int, int] | None:
        """(H, W) of the projector's images written."""
        return grid if self.geometry is None else self.geometry.projector

    def describe_sizes(self) -> str | None:
        """``camera image 40x52 -> 12x16 super-pixels -> projector 24x32``, or None."""
        g = self.geometry
        if g is None:
            return None
        if self.camera_input:
            text = g.describe()
        else:
            text = (f"super-pixel image {g.grid[0]}x{g.grid[1]} -> projector "
                    f"{g.projector[0]}x{g.projector[1]}")
        return text + (" (smoothed)" if self.smooth else "")

    def describe_encoding(self, encoding: FrameEncoding) -> str:
        """The projector response's line, or the line that says there is none."""
        if self.encoder is not None:
            return self.encoder.describe()
        return (f"no projector response: writing linear light encoded as {encoding.name}, "
                f"not projector values -- see {CALIBRATION_SECTION} in the README")

    def to_superpixels(self, frames: np.ndarray) -> np.ndarray:
        """Desired frames (linear light) onto T's images."""
        if self.geometry is None or not self.camera_input:
            return frames
        return self.geometry.to_superpixels(frames)

    def to_projector_light(self, frames: np.ndarray) -> np.ndarray:
        """T's image of linear light onto the projector's pixels."""
        if self.geometry is None:
            return frames
        return self.geometry.to_projector(frames, self.smooth)

    def to_values(self, frames: np.ndarray, encoding: FrameEncoding) -> np.ndarray:
        """The compensation's frames (T's images, linear light above black) -> what is
        written: the projector's codes as [0, 1] values (with a response; the writers
        quantise them back to the same codes), else the light in ``encoding``."""
        light = self.to_projector_light(frames)
        if self.encoder is None:
            return encoding.from_light(light)
        return self.encoder.to_unit(self.encoder.encode(light))

    def sent(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The compensation's frames -> (the projector's image as written, in [0, 1] or
        linear light; the light it sends, on T's images): what ``--simulate`` relights.

        With a response, the light is the projector's for the codes it is sent, above
        black (:meth:`ProjectorEncoder.emitted`); with a geometry, the mean over each
        super-pixel's pixels (what T's column was measured with)."""
        light = self.to_projector_light(frames)
        if self.encoder is None:
            shown, sent = light, light
        else:
            codes = self.encoder.encode(light)
            shown, sent = self.encoder.to_unit(codes), self.encoder.emitted(codes)
        if self.geometry is not None:
            sent = self.geometry.block_means(sent)
        return shown, sent

    def seen_on_camera(self, frames: np.ndarray) -> np.ndarray:
        """What the camera sees, T's images -> the camera's pixels (camera inputs)."""
        if self.geometry is None or not self.camera_input:
            return frames
        return self.geometry.to_camera(frames)


def acquired_transport(X, T):
    """The transport whose rig a compensation works with: ``T`` when given, else the one
    X's record names (when it still exists), else None."""
    if T is not None:
        return T
    path = None if X is None else recorded_transport(X)
    return None if path is None else as_store(path, "T")


def projection_for(X, T, grid, channels: int, *, response="auto", bits: int | None = None,
                   dither: str = "none", seed: int = 0, smooth: bool = False,
                   frame_sizes=()) -> Projection:
    """The :class:`Projection` of a compensation with ``X`` (and ``T``, the transport
    given), whose desired frames are of ``frame_sizes`` (their (H, W) and the path each
    names, for the errors).

    Parameters
    ----------
    X, T : BlockCSR or None
    grid : (H, W) or None, T's (and X's) images
    channels : 1 or 3
    response : ``"auto"`` (the one stored with T), None, a path or a ProjectorResponse
    bits, dither, seed : of the projector (:class:`ProjectorEncoder`); ``bits`` only
        with a response
    smooth : bilinear super-pixels on the projector (a rig's T only)
    frame_sizes : iterable of ((H, W), path)

    Raises
    ------
    ImageError
        A frame of neither the camera's nor the super-pixels' size (naming both), frames
        of both sizes, a response of other channels than T's, ``bits`` without one.
    """
    rig = acquired_transport(X, T)
    geometry = None if rig is None else rig_geometry(rig)
    if geometry is not None and grid is not None and tuple(geometry.grid) != tuple(grid):
        geometry = None  # a T of other images than X's: not this rig
    found = None if rig is None else stored_response_path(rig)
    encoder = projector_encoder(response, bits=bits, dither=dither, seed=seed, found=found)
    if encoder is None and bits is not None:
        raise ImageError("a projector depth ({option}) needs a projector response: give "
                         "one, or store it with T", option=Option("projector_bits", bits))
    if encoder is not None and encoder.channels != channels:
        raise ImageError(f"the projector response has {encoder.channels} channel(s) but the "
                         f"transport {channels}: give the response of this rig")
    camera_input = False
    if geometry is not None:
        kinds = {}
        for size, path in frame_sizes:
            kinds.setdefault(check_camera_or_grid(size, geometry, path), path)
        if len(kinds) > 1:
            raise ImageError("the frames mix the camera's size and the super-pixels': give "
                             "one or the other", Path(kinds["superpixels"]))
        camera_input = "camera" in kinds
    return Projection(geometry, camera_input, encoder, bool(smooth) and geometry is not None)


def image_sizes(files) -> list[tuple[tuple[int, int], Path]]:
    """((H, W), path) of each image file, from its header (None when unreadable: the
    image reader says why later)."""
    sizes = []
    for f in files:
        found = declared_shape(f)
        if found is not None and len(found) >= 2:
            sizes.append((tuple(int(v) for v in found[:2]), Path(f)))
    return sizes
