"""The camera's response: from the values a camera stores to linear light.

A camera stores a code z (an integer 0 .. 2^bits - 1, here always normalised to
z = code / (2^bits - 1) in [0, 1]) for the light x it integrated: z = f(x). bigT needs
f^-1, the *linearisation*, to turn captures into the linear signals a transport
matrix is made of. Four kinds (``--camera-response`` spells them):

=========  ==================================================  =====================
kind       f^-1(z)                                             spelt
=========  ==================================================  =====================
linear     z (RAW captures, scientific cameras)                ``linear``
srgb       the sRGB decoding: z / 12.92 below 0.04045, else    ``srgb``
           ((z + 0.055) / 1.055)^2.4 (IEC 61966-2-1)
gamma      z^G                                                 ``gamma:2.2``
table      table[z (N - 1)], linear interpolation between      a ``.npy`` or ``.json``
           entries; N = 256 (8-bit) or 65536 (16-bit), one     file
           column per channel, non-decreasing
=========  ==================================================  =====================

The formula kinds map full scale to 1. A table is in its own units (a recovered one,
:func:`bigT.calibration.recover_camera_response`, is scaled to 1 at the top code):
only ratios between captures matter to an HDR merge, and the transport inherits the
scale.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import CalibrationError, ImageError, short_reason
from ._files import number_array, read_document, string_list
from ._monotone import invert_table

#: Entries a camera table may have: one per 8-bit or per 16-bit code.
TABLE_SIZES = (256, 65536)
#: The range of G a ``gamma:G`` response may have.
GAMMA_RANGE = (0.1, 10.0)
CHANNEL_NAMES = {1: ("grey",), 3: ("R", "G", "B")}
FORMAT_KIND = "bigT.camera_response"
FORMAT_VERSION = 1
KINDS = ("linear", "srgb", "gamma", "table")


def normalised_codes(image) -> np.ndarray:
    """A capture's codes as z in [0, 1], float64.

    Parameters
    ----------
    image : array_like
        Unsigned integers (z = code / the dtype's largest value: 255 for uint8, 65535
        for uint16) or floats, taken as z already.

    Returns
    -------
    ndarray of float64, the shape of ``image``
    """
    image = np.asarray(image)
    if np.issubdtype(image.dtype, np.unsignedinteger):
        return image.astype(np.float64) / np.iinfo(image.dtype).max
    if np.issubdtype(image.dtype, np.floating):
        return image.astype(np.float64, copy=False)
    raise CalibrationError(f"a capture of type {image.dtype}: unsigned integers or floats")


@dataclass(frozen=True, eq=False)
class CameraResponse:
    """A camera's linearisation f^-1 (module table).

    Attributes
    ----------
    kind : ``"linear"``, ``"srgb"``, ``"gamma"`` or ``"table"``
    gamma : float or None, G of a ``gamma`` response
    table : ndarray, shape (N, C), or None
        A ``table`` response's linear value of each code, N in :data:`TABLE_SIZES`,
        C 1 (every channel alike) or 3, non-decreasing.
    source : str, where it came from (a file, ``"recovered (debevec)"``), for messages
    """

    kind: str = "linear"
    gamma: float | None = None
    table: np.ndarray | None = None
    source: str = ""

    def __post_init__(self):
        if self.kind not in KINDS:
            raise CalibrationError(f"unknown camera response kind {self.kind!r} "
                                   f"(use {', '.join(KINDS)})")
        if (self.kind == "gamma") != (self.gamma is not None):
            raise CalibrationError("a gamma camera response needs its G, and only it has one")
        if (self.kind == "table") != (self.table is not None):
            raise CalibrationError("a table camera response needs its table, and only it has one")
        if self.table is not None:
            table = np.array(self.table, dtype=np.float64)
            table = table[:, None] if table.ndim == 1 else table
            _check_table(table, self.source or None)
            table.setflags(write=False)
            object.__setattr__(self, "table", table)

    def __eq__(self, other) -> bool:
        # the same curve: kind, G and table (compared by value); the source is a label
        if not isinstance(other, CameraResponse):
            return NotImplemented
        same_table = (self.table is None and other.table is None) or (
            self.table is not None and other.table is not None
            and np.array_equal(self.table, other.table))
        return (self.kind, self.gamma) == (other.kind, other.gamma) and same_table

    def __hash__(self) -> int:
        return hash((self.kind, self.gamma, None if self.table is None else self.table.tobytes()))

    @property
    def n_channels(self) -> int:
        """Channels the response distinguishes: a table's columns, else 1 (any image)."""
        return 1 if self.table is None else self.table.shape[1]

    def describe(self) -> str:
        """``"gamma 2.2"``, ``"sRGB"``, ``"linear"``, ``"table of 256 codes x 3
        channels (resp.npy)"``."""
        if self.kind == "table":
            where = f" ({self.source})" if self.source else ""
            return f"table of {self.table.shape[0]} codes x {self.table.shape[1]} channels{where}"
        return f"gamma {self.gamma:g}" if self.kind == "gamma" else {
            "linear": "linear", "srgb": "sRGB"}[self.kind]

    def to_linear(self, image) -> np.ndarray:
        """f^-1: the linear light of a capture's codes.

        Parameters
        ----------
        image : array_like, (H, W) or (H, W, C) (or any shape for a one-channel response)
            Unsigned integer codes or normalised floats (:func:`normalised_codes`).

        Returns
        -------
        ndarray of float64, the shape of ``image``
        """
        z = normalised_codes(image)
        if self.kind == "linear":
            return z.copy()
        if self.kind == "gamma":
            return np.clip(z, 0.0, None) ** self.gamma
        if self.kind == "srgb":
            return np.where(z <= 0.04045, z / 12.92,
                            ((np.clip(z, 0.0, None) + 0.055) / 1.055) ** 2.4)
        codes = np.arange(self.table.shape[0], dtype=np.float64)
        position = np.clip(z, 0.0, 1.0) * (self.table.shape[0] - 1)
        return self._per_channel(position, lambda p, c: np.interp(p, codes, self.table[:, c]))

    def encode(self, linear) -> np.ndarray:
        """f: the normalised code z in [0, 1] a linear light gives (the inverse of
        :meth:`to_linear`; not quantised). The simulated camera
        (:class:`bigT.calibration.NonlinearRig`) uses it."""
        x = np.clip(np.asarray(linear, dtype=np.float64), 0.0, None)
        if self.kind == "linear":
            return np.minimum(x, 1.0)
        if self.kind == "gamma":
            return np.minimum(x, 1.0) ** (1.0 / self.gamma)
        if self.kind == "srgb":
            x = np.minimum(x, 1.0)
            return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
        codes = np.linspace(0.0, 1.0, self.table.shape[0])
        return self._per_channel(x, lambda l, c: invert_table(l, self.table[:, c], codes))

    def _per_channel(self, array, function) -> np.ndarray:
        C = self.table.shape[1]
        if C == 1:
            return function(array, 0)
        if array.ndim == 0 or array.shape[-1] != C:
            raise CalibrationError(f"an image of shape {array.shape} given to a {C}-channel "
                                   f"camera response ({self.describe()})")
        return np.stack([function(array[..., c], c) for c in range(C)], axis=-1)

    def save(self, path: str | os.PathLike) -> Path:
        """Write the response as JSON (docs/CALIBRATION.md), whole or not at all."""
        import json

        from ..atomic import atomic_output

        doc = {"format": FORMAT_KIND, "version": FORMAT_VERSION, "kind": self.kind}
        if self.kind == "gamma":
            doc["gamma"] = self.gamma
        if self.kind == "table":
            doc["channels"] = list(CHANNEL_NAMES[self.table.shape[1]])
            doc["table"] = self.table.tolist()
        path = Path(path)
        with atomic_output(path, "the camera response") as tmp:
            tmp.write_text(json.dumps(doc, allow_nan=False), encoding="utf-8")
        return path


def _check_table(table: np.ndarray, path) -> None:
    if table.ndim != 2 or table.shape[0] not in TABLE_SIZES or table.shape[1] not in (1, 3):
        raise CalibrationError(f"a camera table of shape {table.shape}: it needs "
                               "(256, C) or (65536, C) with C 1 or 3", path)
    if not np.isfinite(table).all():
        raise CalibrationError("the camera table holds a NaN or an infinity", path)
    if np.any(np.diff(table, axis=0) < 0):
        code = int(np.argwhere(np.diff(table, axis=0) < 0)[0, 0])
        raise CalibrationError(f"the camera table falls between codes {code} and {code + 1}: "
                               "a response is non-decreasing", path)
    if not table[-1].min() > 0:
        raise CalibrationError("the camera table's top code is not above 0", path)


def parse_camera_response(spec: str) -> CameraResponse:
    """The camera response a ``--camera-response`` string names.

    Parameters
    ----------
    spec : str
        ``"linear"``, ``"srgb"``, ``"gamma:G"`` (G in :data:`GAMMA_RANGE`), or the path
        of a table: a ``.npy`` array of shape (N,) or (N, C), or a ``.json`` file
        :meth:`CameraResponse.save` wrote.

    Raises
    ------
    CalibrationError
        An unknown spelling, a bad G, a file that is missing or not a response.
    """
    text = str(spec).strip()
    if text.lower() in ("linear", "srgb"):
        return CameraResponse(text.lower())
    if text.lower().startswith("gamma:"):
        return CameraResponse("gamma", gamma=_parse_gamma(text[6:]))
    path = Path(text)
    if path.suffix.lower() == ".npy":
        return CameraResponse("table", table=_load_npy_table(path), source=path.name)
    if path.suffix.lower() == ".json":
        return _load_json(path)
    raise CalibrationError(f"unknown camera response {text[:60]!r} (use linear, srgb, "
                           "gamma:G or a .npy/.json table file)")


def _parse_gamma(text: str) -> float:
    try:
        gamma = float(text)
    except ValueError:
        gamma = float("nan")
    if not GAMMA_RANGE[0] <= gamma <= GAMMA_RANGE[1]:
        raise CalibrationError(f"camera response gamma:{text[:20]}: G must be a number "
                               f"from {GAMMA_RANGE[0]:g} to {GAMMA_RANGE[1]:g}")
    return gamma


def _load_npy_table(path: Path) -> np.ndarray:
    from ..images import declared_shape  # reads the header only: a forged size costs nothing

    try:
        shape = declared_shape(path)
    except ImageError as exc:  # "no such file", re-worded as a calibration error
        raise CalibrationError(exc.problem, path) from None
    if shape is None or len(shape) not in (1, 2) or shape[0] not in TABLE_SIZES or (
            len(shape) == 2 and shape[1] not in (1, 3)):
        raise CalibrationError(f"not a camera table: it declares shape {shape} (need (256,) "
                               "or (65536,), optionally by 1 or 3 channels)", path)
    try:
        table = np.load(path, allow_pickle=False)
    except Exception as exc:  # numpy raises several types on a damaged file
        raise CalibrationError(f"cannot read the table ({short_reason(exc, path)})",
                               path) from None
    if not (np.issubdtype(table.dtype, np.floating) or np.issubdtype(table.dtype, np.integer)):
        raise CalibrationError(f"a camera table of type {table.dtype}: numbers are needed", path)
    table = table.astype(np.float64)
    table = table[:, None] if table.ndim == 1 else table
    _check_table(table, path)
    return table


def _load_json(path: Path) -> CameraResponse:
    doc = read_document(path, FORMAT_KIND, FORMAT_VERSION)
    kind = doc.get("kind")
    if kind not in KINDS:
        raise CalibrationError(f"the field 'kind' must be one of {', '.join(KINDS)}", path)
    if kind == "gamma":
        gamma = number_array(doc, "gamma", 0, path)
        return CameraResponse("gamma", gamma=_parse_gamma(str(float(gamma))))
    if kind != "table":
        return CameraResponse(kind)
    channels = string_list(doc, "channels", path, tuple(CHANNEL_NAMES.values()))
    table = number_array(doc, "table", 2, path)
    if table.ndim != 2 or table.shape[1] != len(channels):
        raise CalibrationError(f"the table's shape {table.shape} does not match its "
                               f"{len(channels)} channels", path)
    _check_table(table, path)
    return CameraResponse("table", table=table, source=path.name)
