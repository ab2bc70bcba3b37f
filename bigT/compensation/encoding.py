"""The encoding of the frames compensation reads and writes: to linear light on the way
in, back to the same encoding on the way out.

T is linear in light, so the desired images are decoded to linear light before the
product and the projector's frames encoded back the same way before they are written
(:mod:`bigT.colour`: ``"srgb"`` or ``"linear"``). Which encoding an input has is the
user's word (``--encoding``) or bigT's policy (``"auto"``,
:func:`bigT.colour.default_encoding`): an 8-bit colour image or video is sRGB-encoded,
16-bit and floating-point ones and every grey one are linear, so grey compensation is
exactly what it was.

The curve runs on float32 frames of the real-time path (X in memory) in a numba kernel
on the kernel threads (numpy's float64 ``power`` takes ~20 ms a 384x512 colour frame,
more than a frame's budget at 60 frames/s); float64 frames go through
:func:`bigT.colour.decode` / :func:`~bigT.colour.encode` themselves.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import colour, config
from ..errors import ImageError, Option
from ..kernels.threads import run_on_threads, thread_count

#: What ``--encoding`` takes: the encodings of :mod:`bigT.colour`, or "auto" (policy).
ENCODING_CHOICES = ("auto", *colour.ENCODINGS)
#: The argument that says an input's encoding, as errors name it.
_ENCODING_OPTION = Option("encoding", "srgb", python="encoding='srgb' or 'linear'")
#: Values below which the numpy functions run (no kernel compiled for a small frame).
_KERNEL_MIN_VALUES = 1 << 16


@dataclass(frozen=True)
class FrameEncoding:
    """The encoding of a compensation's input (and so of its output), and why.

    Attributes
    ----------
    name : one of :data:`bigT.colour.ENCODINGS`
    reason : str, why: ``"asked for"``, ``"8-bit colour input"``, ``"grey input"``...
    """

    name: str
    reason: str

    @property
    def linear(self) -> bool:
        """True when values are light already (nothing to decode or encode)."""
        return self.name == "linear"

    def describe(self) -> str:
        """``encoding srgb (8-bit colour input): decoded to linear light, the projector
        input encoded back``."""
        what = ("values are linear light" if self.linear else
                "decoded to linear light, the projector input encoded back")
        return f"encoding {self.name} ({self.reason}): {what}"

    def to_light(self, frames: np.ndarray) -> np.ndarray:
        """Linear light of ``frames`` (any shape; float32 stays float32)."""
        return frames if self.linear else _apply(frames, self.name, decode=True)

    def from_light(self, frames: np.ndarray) -> np.ndarray:
        """``frames`` of linear light encoded back (any shape, dtype kept)."""
        return frames if self.linear else _apply(frames, self.name, decode=False)


def source_encoding(source, channels: int, requested: str = "auto") -> FrameEncoding:
    """The encoding of an :class:`~bigT.images.ImageSource` or a
    :class:`~bigT.compensation.video.VideoSource` given to a ``channels`` transport.

    ``requested`` other than "auto" wins. Otherwise :func:`bigT.colour.default_encoding`
    of the stored samples: a video's bit depth, each image file's stored type. The frames
    of a folder must agree (else an ImageError naming the first that differs: say which
    with ``--encoding``).
    """
    if requested not in ENCODING_CHOICES:
        raise ImageError(f"unknown image encoding {requested!r} (use "
                         f"{', '.join(ENCODING_CHOICES)})")
    if requested != "auto":
        return FrameEncoding(requested, "asked for")
    if channels == 1:  # grey is linear by policy: no header read
        return FrameEncoding("linear", "grey input")
    info = getattr(source, "info", None)
    if info is not None:  # a video: its stream's bit depth
        name = colour.default_encoding(info.bits, channels)
        return FrameEncoding(name, f"{info.bits}-bit colour video")
    from ..images import image_encoding, stored_type  # only for colour image files

    first = source.files[0]
    name = image_encoding(first, channels)
    for f in source.files[1:]:
        other = image_encoding(f, channels)
        if other != name:
            raise ImageError(f"this frame's encoding would be {other} but the first frame's "
                             f"({first.name}) is {name} (they differ in bit depth): say "
                             "which ({option})", f, option=_ENCODING_OPTION)
    stored = stored_type(first)
    kind = {np.dtype(np.uint8): "8-bit", np.dtype(np.uint16): "16-bit"}.get(
        None if stored is None else np.dtype(stored), "floating-point")
    return FrameEncoding(name, f"{kind} colour input")


def _apply(frames: np.ndarray, name: str, *, decode: bool) -> np.ndarray:
    """decode / encode ``frames`` in ``name``; float32 arrays on the kernel threads."""
    frames = np.asarray(frames)
    if frames.dtype != np.float32 or frames.size < _KERNEL_MIN_VALUES or name != "srgb":
        out = colour.decode(frames, name) if decode else colour.encode(frames, name)
        return out.astype(frames.dtype, copy=False) if frames.dtype.kind == "f" else out
    from . import _encoding_kernels as kernels  # numba: ~0.5 s, only for large float32 frames

    flat = np.ascontiguousarray(frames).reshape(-1)
    out = np.empty_like(flat)
    f = np.float32
    curve = (f(colour.SRGB_SLOPE), f(colour.SRGB_OFFSET), f(1.0 + colour.SRGB_OFFSET))
    if decode:
        args = (f(colour.SRGB_ENCODED_KNEE), *curve, f(colour.SRGB_GAMMA))
        kernel = kernels.srgb_decode
    else:
        args = (f(colour.SRGB_LINEAR_KNEE), *curve, f(1.0 / colour.SRGB_GAMMA))
        kernel = kernels.srgb_encode
    threads = thread_count()
    step = -(-flat.size // (threads * config.KERNEL_CHUNKS_PER_THREAD))
    ranges = [(a, min(a + step, flat.size)) for a in range(0, flat.size, step)]
    run_on_threads(lambda a, b: kernel(flat, out, a, b, *args), ranges, threads)
    return out.reshape(frames.shape)
