"""Video files in and out of compensation, streamed frame by frame through ffmpeg.

Reading and writing go through ``imageio-ffmpeg`` (imageio's ffmpeg plugin, which
ships its own ffmpeg binary): one ffmpeg process decodes the input into raw frames on a
pipe (``imageio_ffmpeg.read_frames``), another encodes the projector frames from a
pipe; neither the video nor its frames are ever all in memory.

A video is read for a transport of 1 (grey) or 3 (RGB) channels, as images are
(:mod:`bigT.images`), as floats in [0, 1] in the stream's own encoding
(:mod:`bigT.colour`: an 8-bit colour stream is sRGB-encoded by default):

* grey (``channels=1``): a frame is read as its luma (ffmpeg's ``gray``, or
  ``gray16le`` for a stream of more than 8 bits), shape (H, W). A video whose first
  frame has colour (its RGB channels differ by more than :data:`COLOUR_TOLERANCE` levels
  of 255) is refused; an RGB stream of grey pictures, and the neutral chroma of a YUV
  stream, are accepted.
* colour (``channels=3``): a frame is read as RGB (``rgb24``, or ``rgb48le`` for a
  stream of more than 8 bits), shape (H, W, 3). A grey stream (a ``gray*`` pixel
  format) is refused; a colour stream of grey pictures is colour that happens to be
  neutral, and is accepted.

Writing (whole or nothing, through :func:`bigT.atomic.atomic_output`) is lossless:

==================  ==============================================  ===========
suffix              codec, grey / colour                            bit depth
==================  ==============================================  ===========
``.mkv``, ``.avi``  FFV1, gray / gray16le; bgr0 / rgb48le           8 or 16
``.mp4``, ``.mov``  H.264 at ``-qp 0``: libx264 gray, full range;   8
                    libx264rgb (RGB planes, no YUV conversion)
==================  ==============================================  ===========

so a projector frame comes back exactly as it was quantised to 8 (or 16) bits.
"""

from __future__ import annotations

import contextlib
import os
import re
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from ..atomic import atomic_output
from ..errors import ImageError, OutputError

#: File name suffixes read and written as video (lower case).
VIDEO_SUFFIXES = (".mp4", ".m4v", ".mov", ".mkv", ".avi")
#: Suffixes written with FFV1 (8 or 16 bits); the others with lossless H.264 (8 bits).
FFV1_SUFFIXES = (".mkv", ".avi")
#: Largest channel difference (levels of 255) of a frame still read as gray: the
#: rounding of a YUV stream's neutral chroma back to RGB.
COLOUR_TOLERANCE = 3
#: Frames per second of a video written from a source that has none.
DEFAULT_FPS = 30.0


def is_video_file(path: str | os.PathLike) -> bool:
    """True when ``path`` has one of :data:`VIDEO_SUFFIXES`."""
    return Path(path).suffix.lower() in VIDEO_SUFFIXES


@dataclass(frozen=True)
class VideoInfo:
    """What ffmpeg says of a video's first stream.

    Attributes
    ----------
    shape : (H, W)
    fps : float
    frames : int or None, an estimate (duration x fps) where the container has one.
    pix_fmt : str, the stream's pixel format ("yuv420p", "gray"...).
    bits : int, 8 or 16: how the frames are read (and written back by default).
    codec : str
    channels : int, 1 for a stream of a grey pixel format (``gray``, ``gray16le``...),
        3 for any other.
    spread : int, the largest difference between two RGB channels of the first frame,
        in levels of 255 (at most :data:`COLOUR_TOLERANCE` for grey pictures).
    """

    shape: tuple
    fps: float
    frames: int | None
    pix_fmt: str
    bits: int
    codec: str
    channels: int = 1
    spread: int = 0


#: Lines of ffmpeg's log that say nothing about the file: its version banner (version,
#: compiler, configuration, library versions), the indented stream and metadata
#: descriptions, progress lines, and its hints and format-guess warnings.
_FFMPEG_CHATTER = re.compile(r"\s|ffmpeg version|Input #|Output #|Press \[q\]|frame=|size="
                             r"|video:|Consider increasing|.*misdetection possible!$")
#: The log line after which ffmpeg reports on its outputs, no longer on the input.
_FFMPEG_OUTPUT_SIDE = "Stream mapping:"
#: imageio-ffmpeg's own headline when ffmpeg printed no stream header: the log says why.
_NO_HEADER = "Could not load meta information"
#: Complaints of ffmpeg's log kept as the cause.
FFMPEG_CAUSE_LINES = 2


def _reason(exc: BaseException, path) -> str:
    """Why ffmpeg could not read ``path``, in one line: the complaints of its log
    (:func:`ffmpeg_cause`), after imageio-ffmpeg's own headline where it says more than
    that it failed."""
    head, _, log = str(exc).partition("=== stderr ===")
    head = re.sub(r"FFMPEG COMMAND:.*?FFMPEG STDERR OUTPUT:", "", head, flags=re.S)
    parts = [" ".join(head.split())] if _NO_HEADER not in head else []
    parts += ffmpeg_cause(log, path)
    text = "; ".join(p for p in parts if p)
    return (text or type(exc).__name__)[:300]


def ffmpeg_cause(log: str, path) -> list[str]:
    """The lines of an ffmpeg log that say what is wrong with the input ``path``.

    ffmpeg prints its version banner first, then each component's complaints prefixed
    by its name (``[in#0/mov,mp4 @ 0x55...] moov atom not found``). The reader of the
    input complains first and says why (``File ended prematurely``); the filters and
    encoders after it then fail in turn for want of frames, and the callers above a
    complaint repeat its final clause (``Error opening input: Invalid data...``, then
    ``Error opening input files: Invalid data...``). So: the first distinct complaints
    about the input, else the last ones of the log.

    Returns
    -------
    list of str
        At most :data:`FFMPEG_CAUSE_LINES`, without component prefixes, ``path``
        shortened to its name.
    """
    name, full = Path(path).name, os.fspath(path)
    inputs: list[str] = []
    others: list[str] = []
    seen: set[str] = set()
    output_side = False
    for line in log.splitlines():
        output_side = output_side or line.startswith(_FFMPEG_OUTPUT_SIDE)
        if not line.strip() or _FFMPEG_CHATTER.match(line):
            continue
        prefixes = re.match(r"(\[[^\]]*@ 0x[0-9a-f]+\]\s*)*", line.strip()).group(0)
        text = line.strip()[len(prefixes):].replace(full, name)
        clause = text.rsplit(": ", 1)[-1]
        if not text or clause in seen or text.startswith(f"Error opening input file {name}"):
            continue
        seen.add(clause)
        on_input = prefixes.startswith("[in#") or not (output_side or prefixes)
        (inputs if on_input else others).append(text)
    return inputs[:FFMPEG_CAUSE_LINES] or others[-FFMPEG_CAUSE_LINES:]


def _deep(pix_fmt: str) -> bool:
    """A stream of more than 8 bits per sample (read as 16-bit gray)."""
    return bool(re.search(r"(16|12|10|14|9)(le|be)\b|p(16|12|10|14|9)|48|64", pix_fmt))


def _grey_pix_fmt(pix_fmt: str) -> bool:
    """A pixel format of one luma plane (with alpha or not): a stream of grey pictures."""
    return pix_fmt.startswith(("gray", "ya8", "ya16", "mono"))


def probe_video(path: str | os.PathLike) -> VideoInfo:
    """Open ``path`` with ffmpeg and return its :class:`VideoInfo` (no frame decoded
    but the first, for its colour spread).

    Raises
    ------
    ImageError
        Missing, unreadable, or no video stream (colour is the reader's call:
        :class:`VideoSource`).
    """
    import imageio_ffmpeg  # locates its ffmpeg binary on import: only for video

    path = Path(path)
    if not path.is_file():
        raise ImageError("no such file" if not path.exists() else "is not a file", path)
    gen = imageio_ffmpeg.read_frames(str(path), pix_fmt="rgb24", bits_per_pixel=24,
                                     output_params=["-frames:v", "1"])
    try:
        meta = next(gen)
        first = next(gen, None)
    except Exception as exc:  # imageio-ffmpeg raises IOError/RuntimeError on bad files
        raise ImageError(f"cannot read the video ({_reason(exc, path)})", path) from None
    finally:
        gen.close()
    W, H = (int(s) for s in meta.get("source_size") or meta["size"])
    if first is None:
        raise ImageError("the video has no frames", path)
    rgb = np.frombuffer(first, np.uint8).reshape(H, W, 3).astype(np.int16)
    spread = int(max(np.abs(rgb[..., 0] - rgb[..., 1]).max(),
                     np.abs(rgb[..., 1] - rgb[..., 2]).max()))
    pix_fmt = str(meta.get("pix_fmt", "")).split("(")[0].strip()
    fps = float(meta.get("fps") or DEFAULT_FPS)
    duration = float(meta.get("duration") or 0.0)
    frames = int(round(duration * fps)) if duration > 0 else None
    return VideoInfo((H, W), fps, frames, pix_fmt, 16 if _deep(pix_fmt) else 8,
                     str(meta.get("codec", "")).strip(", "),
                     channels=1 if _grey_pix_fmt(pix_fmt) else 3, spread=spread)


def check_video_channels(info: VideoInfo, channels: int, path) -> None:
    """Refuse a colour video given to a grey transport, or a grey one to a colour
    transport, in one line naming ``path``.

    Raises
    ------
    ImageError
    """
    if channels not in (1, 3):
        raise ImageError(f"a transport has 1 (grey) or 3 (RGB) channels, not {channels!r}", path)
    if channels == 1 and info.spread > COLOUR_TOLERANCE:
        raise ImageError(f"colour video (channels of the first frame differ by up to "
                         f"{info.spread} levels) given to a grey transport (1 channel): "
                         "convert it to grey first, or use a colour transport", path)
    if channels == 3 and info.channels == 1:
        raise ImageError(f"grey video (pixel format {info.pix_fmt}) given to a colour "
                         "transport (3 channels): give a colour video, or use a grey "
                         "transport", path)


class VideoSource:
    """The frames of a video file, decoded one at a time.

    Parameters
    ----------
    path : the video file.
    shape : (H, W), optional, the size every frame must have (checked on the stream's
        header, before any frame is read).
    channels : {1, 3}
        The transport's: frames are read grey (H, W) or RGB (H, W, 3); a video of the
        other kind is refused (:func:`check_video_channels`). Grey by default, as
        bigT's transports were before colour.

    Attributes
    ----------
    info : VideoInfo
    channels : int
    is_folder : False (a source for :class:`bigT.images.ImageSink` rules)
    """

    is_folder = False

    def __init__(self, path: str | os.PathLike, shape: Sequence[int] | None = None,
                 channels: int = 1):
        self.path = Path(path)
        self.info = probe_video(self.path)
        if shape is not None and tuple(self.info.shape) != tuple(shape):
            raise ImageError(f"frames of shape {self.info.shape} do not match the transport's "
                             f"image shape {tuple(shape)}", self.path)
        check_video_channels(self.info, channels, self.path)
        self.channels = int(channels)

    @property
    def frame_shape(self) -> tuple[int, ...]:
        """(H, W), or (H, W, 3) for colour."""
        return self.info.shape if self.channels == 1 else (*self.info.shape, 3)

    def __len__(self) -> int:
        return self.info.frames or 0

    @property
    def code_dtype(self) -> np.dtype:
        """uint8, or uint16 for a stream of more than 8 bits: the codes as read."""
        return np.dtype(np.uint16 if self.info.bits == 16 else np.uint8)

    def frames(self) -> Iterator[np.ndarray]:
        """Yield each frame, shape (H, W) (grey) or (H, W, 3) (colour), float32 in
        [0, 1]."""
        scale = np.float32(1.0 / np.iinfo(self.code_dtype).max)
        for codes in self.codes():
            yield codes.astype(np.float32) * scale

    def codes(self) -> Iterator[np.ndarray]:
        """Yield each frame as ffmpeg decodes it: shape (H, W) or (H, W, 3), of
        :attr:`code_dtype` (read-only: a view of the pipe's bytes)."""
        import imageio_ffmpeg  # finds its ffmpeg binary on import: only for video

        dtype = self.code_dtype
        bits = 8 * dtype.itemsize
        gen = imageio_ffmpeg.read_frames(str(self.path), pix_fmt=_RAW_FORMATS[self.channels, bits],
                                         bits_per_pixel=self.channels * bits)
        try:
            next(gen)  # the metadata, read by probe_video
            for raw in _checked(gen, self.path):
                yield np.frombuffer(raw, dtype).reshape(self.frame_shape)
        finally:
            gen.close()

    def code_batches(self, size: int) -> Iterator[tuple[list[int], np.ndarray]]:
        """(frame numbers, codes) batches of ``size`` frames (the last may be shorter),
        codes of shape (k, *frame_shape) and :attr:`code_dtype`."""
        size = max(1, int(size))
        batch = np.empty((size, *self.frame_shape), self.code_dtype)
        k = first = 0
        for i, frame in enumerate(self.codes()):
            batch[k] = frame
            k += 1
            if k == size:
                yield list(range(first, i + 1)), batch
                # a new array each batch: the last is still in the queue or the products
                batch, k, first = np.empty_like(batch), 0, i + 1
        if k:
            yield list(range(first, first + k)), batch[:k]


#: ffmpeg's raw pixel format of a frame on a pipe, by (channels, bits): native order
#: (little-endian) so numpy reads it as it comes.
_RAW_FORMATS = {(1, 8): "gray", (1, 16): "gray16le", (3, 8): "rgb24", (3, 16): "rgb48le"}


def _checked(gen, path):
    """The generator's items; its failures as one-line ImageErrors naming ``path``."""
    while True:
        try:
            item = next(gen)
        except StopIteration:
            return
        except Exception as exc:
            raise ImageError(f"cannot read the video ({_reason(exc, path)})", path) from None
        yield item


class VideoSink:
    """A video file written frame by frame, in place only once complete.

    Use as a context manager; leaving it by an exception discards everything written.
    The frames go to imageio-ffmpeg's ffmpeg on a pipe (a process of our own rather
    than ``imageio_ffmpeg.write_frames``, which does not check ffmpeg's exit status: a
    file ffmpeg could not finish must not be renamed into place).

    Parameters
    ----------
    path : the output video (a suffix of :data:`VIDEO_SUFFIXES`).
    shape : (H, W)
    fps : float
    bits : {8, 16}, 16 only for :data:`FFV1_SUFFIXES`.
    channels : {1, 3}, grey or RGB frames.
    """

    def __init__(self, path: str | os.PathLike, shape: Sequence[int], fps: float,
                 bits: int = 8, channels: int = 1):
        self.path = Path(path)
        suffix = self.path.suffix.lower()
        if suffix not in VIDEO_SUFFIXES:
            raise ImageError(f"the input is a video, so the output must be one too "
                             f"({', '.join(VIDEO_SUFFIXES)}), not {suffix or 'no suffix'!r}",
                             self.path)
        if self.path.is_dir():
            raise OutputError("is a folder; the output video is a file: choose a file name",
                              self.path)
        if bits not in (8, 16) or (bits == 16 and suffix not in FFV1_SUFFIXES):
            raise ImageError(f"{bits}-bit video is written as {', '.join(FFV1_SUFFIXES)} "
                             "(FFV1); .mp4/.mov hold 8 bits", self.path)
        if channels not in (1, 3):
            raise ImageError(f"a video has 1 (grey) or 3 (RGB) channels, not {channels!r}",
                             self.path)
        self.shape = tuple(int(s) for s in shape)
        self.channels = int(channels)
        self.frame_shape = self.shape if channels == 1 else (*self.shape, 3)
        self.fps = float(fps)
        self.bits = int(bits)
        self.frames_written = 0
        self._stack: contextlib.ExitStack | None = None
        self._proc = None
        self._log = None

    def _command(self, tmp: Path) -> list[str]:
        import imageio_ffmpeg  # finds its ffmpeg binary on import: only for video

        H, W = self.shape
        fmt = _RAW_FORMATS[self.channels, self.bits]
        ffv1 = self.path.suffix.lower() in FFV1_SUFFIXES
        if ffv1 and self.channels == 1:
            codec = ["-c:v", "ffv1", "-pix_fmt", fmt]
        elif ffv1:  # FFV1's RGB layouts: 8 bits padded to 32, or 16 bits as they come
            codec = ["-c:v", "ffv1", "-pix_fmt", "bgr0" if self.bits == 8 else "rgb48le"]
        elif self.channels == 1:  # qp 0: lossless H.264; gray keeps the full range
            codec = ["-c:v", "libx264", "-qp", "0", "-preset", "ultrafast", "-pix_fmt", "gray"]
        else:  # libx264rgb codes the RGB planes themselves: no lossy RGB -> YUV step
            codec = ["-c:v", "libx264rgb", "-qp", "0", "-preset", "ultrafast",
                     "-pix_fmt", "rgb24"]
        return [imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-f", "rawvideo",
                "-pix_fmt", fmt, "-s", f"{W}x{H}", "-r", f"{self.fps:.6g}", "-i", "-", "-an",
                *codec, str(tmp)]

    def __enter__(self) -> "VideoSink":
        self._stack = contextlib.ExitStack()
        try:
            tmp = self._stack.enter_context(atomic_output(self.path, "the video"))
            self._log = self._stack.enter_context(tempfile.TemporaryFile())
            self._proc = subprocess.Popen(self._command(tmp), stdin=subprocess.PIPE,
                                          stdout=subprocess.DEVNULL, stderr=self._log)
        except BaseException:
            self._stack.__exit__(*sys.exc_info())
            raise
        return self

    def write(self, frames: np.ndarray) -> None:
        """Append frames, shape (K, H, W) or (H, W) (grey), (K, H, W, 3) or (H, W, 3)
        (colour), values in [0, 1] (clipped and rounded to the sink's bit depth)."""
        dtype = self.code_dtype
        # one pass of float32 arithmetic over the batch (float32 keeps 65535 levels)
        scaled = np.clip(np.asarray(frames, np.float32).reshape(-1, *self.frame_shape), 0.0, 1.0)
        scaled *= np.float32(np.iinfo(dtype).max)
        self.write_codes(np.rint(scaled, out=scaled).astype(dtype))

    @property
    def code_dtype(self) -> np.dtype:
        """uint8, or uint16 for 16 bits: the codes :meth:`write_codes` takes."""
        return np.dtype(np.uint16 if self.bits == 16 else np.uint8)

    def write_codes(self, codes: np.ndarray) -> None:
        """Append frames of integer codes, shape (K, *frame_shape) or one frame, of
        :attr:`code_dtype` (written as they are: no copy of a C-contiguous batch)."""
        codes = np.ascontiguousarray(codes).reshape(-1, *self.frame_shape)
        if codes.dtype != self.code_dtype:
            raise ImageError(f"codes of {codes.dtype} given to a {self.bits}-bit video",
                             self.path)
        for frame in codes:
            try:
                self._proc.stdin.write(memoryview(frame).cast("B"))
            except OSError:  # ffmpeg is gone (a full disk, say): its words say why
                self._proc.wait()
                raise OutputError(f"cannot write the video ({self._ffmpeg_says()}); nothing "
                                  "was replaced", self.path) from None
            self.frames_written += 1

    def _ffmpeg_says(self) -> str:
        self._log.seek(0)
        text = " ".join(self._log.read().decode("utf-8", "replace").split())
        return (text or f"ffmpeg exit status {self._proc.returncode}")[-200:]

    def _finish(self, failed: bool) -> None:
        proc, self._proc = self._proc, None
        if proc is None:
            return
        if failed:
            proc.kill()
            proc.wait()
            return
        with contextlib.suppress(OSError):
            proc.stdin.close()
        self._proc = proc
        status = proc.wait()
        if status != 0 or self.frames_written == 0:
            why = self._ffmpeg_says() if self.frames_written else "no frames"
            raise OutputError(f"cannot write the video ({why}); nothing was replaced",
                              self.path)
        self._proc = None

    def __exit__(self, exc_type, exc, tb) -> bool:
        try:
            self._finish(failed=exc_type is not None)
        except BaseException:
            self._stack.__exit__(*sys.exc_info())  # the temporary file goes
            raise
        return bool(self._stack.__exit__(exc_type, exc, tb))
