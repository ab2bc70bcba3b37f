"""What a pattern folder holds: :class:`Pattern` and :class:`Manifest` (``manifest.json``).

A projector of ``H x W`` pixels is cut into super-pixels of ``s x s`` pixels (paper
§6.1 groups 4x4 or 2x2 projector pixels); the super-pixel grid is ``(H/s, W/s)`` and a
super-pixel's *index* is its row-major position in that grid. The manifest lists, in
the order they are to be projected, every pattern image of the folder and what it
lights; a captures folder holds one camera image per pattern under the same ``file``
name (suffix free: ``.png``, ``.tif``, ``.npy``).

Kinds of pattern
----------------
``black``, ``white``
    Nothing lit (the camera's black level) and everything lit (validation, paper Fig. 8;
    Gray-code shadow mask).
``superpixel``
    Brute force: one super-pixel lit; ``index`` says which.
``row-stripe``, ``col-stripe``
    Stripe scanning (Ding et al. 2009): one band of super-pixel rows (``band`` = the
    grid row) or columns (``band`` = the grid column) lit.
``ramp``
    A uniform frame at ``level`` (in [0, 1], an exact 8-bit code: k / 255), the ramp
    the projector's response is fitted from (docs/CALIBRATION.md "Capturing");
    ``--ramp-levels`` levels from 0 to 1, in a colour set once per primary (``primary``
    lit at ``level``, the other two at 0: ``ramp_04_G.png``). A manifest records the
    count as ``ramp_levels`` (absent: no ramp, the sets bigT wrote before).
``graycode``
    Structured light: the super-pixels whose ``axis`` ("col" or "row") coordinate has a
    Gray code with bit ``bit`` set (``bit`` 0 is the most significant, as OpenCV's
    ``structured_light.GrayCodePattern`` orders them) are lit, or the others when
    ``inverted``.

Colour (``channels: 3``)
------------------------
Each ``superpixel``, ``row-stripe`` and ``col-stripe`` pattern is listed once per
projector primary (``primary``: "R", "G" or "B"; the image is lit in that primary
only, file ``sp_005_R.png``), so T's column 3 q + j is the light of primary j from
super-pixel q. ``black``, ``white`` and the Gray code have no primary: they are lit in
all three (white), the Gray code being geometry only. A grey manifest records no
``channels`` (it reads as 1), so grey pattern sets are written as they always were.
"""

from __future__ import annotations

import json
import math
import os
import stat
from dataclasses import dataclass
from pathlib import Path

from ..atomic import atomic_output
from ..errors import AcquisitionError

MANIFEST = "manifest.json"
FORMAT = "bigT-acquisition-patterns"
VERSION = 1
METHODS = ("brute-force", "stripes", "graycode")
#: The most patterns bigT lists: brute force on a 3840x2160 projector in 1x1 super-pixels
#: (8.3 M, days of capturing) fits; a manifest edited to a far larger projector is
#: refused at once instead of being rebuilt pattern by pattern to compare.
MAX_PATTERNS = 1 << 23
KINDS = ("black", "white", "ramp", "superpixel", "row-stripe", "col-stripe", "graycode")
AXES = ("col", "row")
#: The projector primaries of a colour pattern set, in T's column order (3 q + j).
PRIMARIES = ("R", "G", "B")
#: Kinds measuring T's columns: listed once per primary in a colour set.
TRANSPORT_KINDS = ("superpixel", "row-stripe", "col-stripe")
#: Channels a pattern set may have: grey, or the three primaries.
CHANNEL_COUNTS = (1, 3)
#: Ramp levels a pattern set may have: none, or MIN_RAMP_LEVELS (17: 1/16 steps, so
#: the fitted response's interpolation error stays near 3e-4 of full scale,
#: docs/CALIBRATION.md) to 256 (every 8-bit code: the patterns are 8-bit PNGs).
MIN_RAMP_LEVELS, MAX_RAMP_LEVELS = 17, 256
DEFAULT_RAMP_LEVELS = MIN_RAMP_LEVELS


@dataclass(frozen=True)
class Pattern:
    """One pattern image and what it lights.

    Attributes
    ----------
    file : str
        File name of the pattern (``.png``) in the pattern folder; the capture of it has
        the same stem.
    kind : one of :data:`KINDS`
    index : int or None, the lit super-pixel (``superpixel``)
    band : int or None, the lit grid row or column (``row-stripe``/``col-stripe``)
    axis : {"col", "row"} or None, the coordinate a ``graycode`` pattern encodes
    bit : int or None, the Gray-code bit, 0 = most significant
    inverted : bool or None, a ``graycode`` pattern's complement
    primary : {"R", "G", "B"} or None, the one primary lit (a colour set's
        ``superpixel``, stripe and ramp patterns); None: all lit (white) or a grey set
    level : float or None, a ``ramp`` pattern's uniform value in [0, 1] (k / 255)
    """

    file: str
    kind: str
    index: int | None = None
    band: int | None = None
    axis: str | None = None
    bit: int | None = None
    inverted: bool | None = None
    primary: str | None = None
    level: float | None = None

    @property
    def stem(self) -> str:
        return Path(self.file).stem

    @property
    def primary_index(self) -> int:
        """T's column offset j of the primary lit (0 for a grey pattern)."""
        return 0 if self.primary is None else PRIMARIES.index(self.primary)

    def to_dict(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if v is not None}


@dataclass(frozen=True)
class Manifest:
    """The patterns of one acquisition, in projection order.

    Attributes
    ----------
    projector : (int, int), the projector's (H, W) in pixels
    superpixel : int, side s of a super-pixel in projector pixels (H and W multiples of s)
    method : one of :data:`METHODS`, how T's columns are measured
    graycode : bool, Gray-code patterns included (the correspondence by decoding)
    patterns : tuple of Pattern
    channels : {1, 3}, 3 for a colour set (each transport pattern once per primary)
    ramp_levels : int, levels of the projector-response ramp (0: none)
    """

    projector: tuple[int, int]
    superpixel: int
    method: str
    graycode: bool
    patterns: tuple[Pattern, ...]
    channels: int = 1
    ramp_levels: int = 0

    @property
    def grid(self) -> tuple[int, int]:
        """(H/s, W/s): the super-pixel grid; T is n x n with n = its product (times the
        channels for colour)."""
        return (self.projector[0] // self.superpixel, self.projector[1] // self.superpixel)

    @property
    def n(self) -> int:
        """Super-pixels of the grid (T's side is ``channels`` times this)."""
        return self.grid[0] * self.grid[1]

    def primaries(self) -> tuple[str | None, ...]:
        """What each transport pattern is lit in: (None,) grey, ("R", "G", "B") colour."""
        return (None,) if self.channels == 1 else PRIMARIES

    def of_kind(self, kind: str) -> list[Pattern]:
        return [p for p in self.patterns if p.kind == kind]

    def single(self, kind: str) -> Pattern:
        """The one pattern of ``kind`` (``black`` or ``white``)."""
        return self.of_kind(kind)[0]

    def ramp(self) -> list[Pattern]:
        """The ``ramp`` patterns, by primary (grey: one run) then rising level."""
        return self.of_kind("ramp")

    def graycode_bits(self, axis: str) -> int:
        """Bits of the Gray code of a grid coordinate along ``axis``."""
        size = self.grid[1] if axis == "col" else self.grid[0]
        return graycode_bits(size)

    def to_dict(self) -> dict:
        colour = {} if self.channels == 1 else {"channels": self.channels}
        ramp = {"ramp_levels": self.ramp_levels} if self.ramp_levels else {}
        return {"format": FORMAT, "version": VERSION, "projector": list(self.projector),
                "superpixel": self.superpixel, "grid": list(self.grid),
                "method": self.method, "graycode": self.graycode, **colour, **ramp,
                "patterns": [p.to_dict() for p in self.patterns]}

    @classmethod
    def from_dict(cls, d: dict, path) -> "Manifest":
        """Parse and check a manifest; every problem is an AcquisitionError naming ``path``."""
        def bad(what):
            return AcquisitionError(f"not a valid bigT pattern manifest: {what}", path)

        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise bad(f"'format' is not {FORMAT!r}")
        if d.get("version") != VERSION:
            raise bad(f"version {d.get('version')!r:.40}, this bigT reads version {VERSION}")
        try:
            projector = tuple(_count(v, "projector") for v in d["projector"])
            superpixel = _count(d["superpixel"], "superpixel")
            method, graycode = d["method"], d["graycode"]
            channels = d.get("channels", 1)
            ramp_levels = d.get("ramp_levels", 0)
            patterns = tuple(_pattern(p) for p in d["patterns"])
        except (KeyError, TypeError, ValueError) as exc:
            raise bad(str(exc) if not isinstance(exc, KeyError) else f"no {exc}") from None
        if method not in METHODS or not isinstance(graycode, bool) or len(projector) != 2:
            raise bad("method, graycode or projector has a wrong value")
        if isinstance(channels, bool) or channels not in CHANNEL_COUNTS:
            raise bad(f"channels {channels!r:.40} is not 1 (grey) or 3 (R, G, B)")
        if not _valid_ramp_levels(ramp_levels):
            raise bad(f"ramp_levels {ramp_levels!r:.40} is not 0 or {MIN_RAMP_LEVELS} to "
                      f"{MAX_RAMP_LEVELS}")
        manifest = cls(projector, superpixel, method, graycode, patterns, channels,
                       ramp_levels)
        try:
            check_geometry(projector, superpixel)
            # counted first: a huge projector is refused at once, not listed to compare
            count = checked_pattern_count(method, projector, superpixel, graycode=graycode,
                                          channels=channels, ramp_levels=ramp_levels)
        except AcquisitionError as exc:  # super-pixels not dividing it, too many patterns
            raise AcquisitionError(f"not a valid bigT pattern manifest: {exc.template}", path,
                                   option=exc.option) from None
        if count != len(patterns):
            raise bad(f"the pattern list is not the one bigT writes for its method and size "
                      f"({len(patterns)} patterns listed, {count} expected)")
        expected = make_manifest(method, projector, superpixel, graycode=graycode,
                                 channels=channels, ramp_levels=ramp_levels)
        if manifest != expected:
            raise bad("the pattern list is not the one bigT writes for its method and size")
        # the canonical one: equal is not identical (an index of 5.0 equals 5 but is no
        # array index, inverted: 1 equals True)
        return expected


def _count(value, what) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{what} must be a positive integer, got {value!r:.40}")
    return value


def _pattern(d) -> Pattern:
    if not isinstance(d, dict) or d.get("kind") not in KINDS or not isinstance(d.get("file"), str):
        # the entry's text cut short: an entry may be as large as the file
        raise ValueError(f"pattern entry {d!r:.80} has no valid 'kind' and 'file'")
    return Pattern(**{k: d.get(k) for k in Pattern.__dataclass_fields__})


def _valid_ramp_levels(levels) -> bool:
    return (isinstance(levels, int) and not isinstance(levels, bool)
            and (levels == 0 or MIN_RAMP_LEVELS <= levels <= MAX_RAMP_LEVELS))


def ramp_values(levels: int) -> list[float]:
    """The ramp's ``levels`` values, rising from 0 to 1, each an exact 8-bit code k / 255
    (k = round(i 255 / (levels - 1))): what an 8-bit pattern file holds is the level
    the manifest records."""
    return [round(i * 255 / (levels - 1)) / 255 for i in range(levels)]


def graycode_bits(size: int) -> int:
    """Bits needed to number ``size`` positions (at least 1)."""
    return max(1, math.ceil(math.log2(size)))


def check_geometry(projector, superpixel: int) -> None:
    """AcquisitionError unless the projector's sides are positive multiples of s."""
    h, w = projector
    if superpixel < 1 or h < superpixel or w < superpixel or h % superpixel or w % superpixel:
        raise AcquisitionError(
            f"the projector's {h}x{w} pixels do not divide into {superpixel}x{superpixel} "
            "super-pixels: choose a {option} dividing both sides", option="superpixel")


def pattern_count(method: str, projector, superpixel: int = 1, *,
                  graycode: bool | None = None, channels: int = 1, ramp_levels: int = 0) -> int:
    """How many patterns :func:`make_manifest` lists, without listing them."""
    gh, gw = int(projector[0]) // superpixel, int(projector[1]) // superpixel
    count = 2 + channels * ({"brute-force": gh * gw, "stripes": gh + gw}.get(method, 0)
                            + ramp_levels)
    if method == "graycode" or graycode:
        count += 2 * (graycode_bits(gw) + graycode_bits(gh))
    return count


def checked_pattern_count(method: str, projector, superpixel: int = 1, *,
                          graycode: bool | None = None, channels: int = 1,
                          ramp_levels: int = 0) -> int:
    """:func:`pattern_count`, refused (AcquisitionError) above :data:`MAX_PATTERNS`."""
    count = pattern_count(method, projector, superpixel, graycode=graycode,
                          channels=channels, ramp_levels=ramp_levels)
    if count > MAX_PATTERNS:
        raise AcquisitionError(
            f"{method} on a {projector[0]}x{projector[1]} projector in {superpixel}x"
            f"{superpixel} super-pixels needs {count} patterns, more than bigT lists "
            f"({MAX_PATTERNS}): choose a larger {{option}} or the stripes method",
            option="superpixel")
    return count


def make_manifest(method: str, projector, superpixel: int = 1, *,
                  graycode: bool | None = None, channels: int = 1,
                  ramp_levels: int = 0) -> Manifest:
    """The patterns bigT projects for ``method``.

    Parameters
    ----------
    method : one of :data:`METHODS`
    projector : (int, int), the projector's (H, W) in pixels
    superpixel : int, super-pixel side s (H and W multiples of s)
    graycode : bool, optional
        Add the Gray-code patterns (the ``graycode`` method always has them; brute
        force and stripes then take the correspondence from them rather than from the
        maximum response). Default: only for the ``graycode`` method.
    channels : {1, 3}
        3 for a colour set: each super-pixel or stripe pattern once per projector
        primary (R, G, B, in that order, one after the other).

    Returns
    -------
    Manifest
        Black and white first, then the method's patterns, then the Gray code (column
        bits then row bits, each pattern followed by its inverse).

    Raises
    ------
    AcquisitionError
        An unknown method, super-pixels not dividing the projector, more than
        :data:`MAX_PATTERNS` patterns, channels other than 1 or 3.
    """
    if method not in METHODS:
        raise AcquisitionError(f"unknown method {method!r} (one of {', '.join(METHODS)})")
    if isinstance(channels, bool) or channels not in CHANNEL_COUNTS:
        raise AcquisitionError(f"channels must be 1 (grey) or 3 (R, G, B), got {channels!r:.40}")
    if not _valid_ramp_levels(ramp_levels):
        raise AcquisitionError(f"{{option}} must be 0 (no ramp) or {MIN_RAMP_LEVELS} to "
                               f"{MAX_RAMP_LEVELS}, got {ramp_levels!r:.40}",
                               option="ramp_levels")
    projector = (int(projector[0]), int(projector[1]))
    check_geometry(projector, superpixel)
    checked_pattern_count(method, projector, superpixel, graycode=graycode, channels=channels,
                          ramp_levels=ramp_levels)
    graycode = method == "graycode" or bool(graycode)
    gh, gw = projector[0] // superpixel, projector[1] // superpixel
    primaries = (None,) if channels == 1 else PRIMARIES

    def per_primary(stem: str, kind: str, **where) -> list[Pattern]:
        return [Pattern(f"{stem}{'' if j is None else '_' + j}.png", kind, primary=j, **where)
                for j in primaries]

    patterns = [Pattern("black.png", "black"), Pattern("white.png", "white")]
    if ramp_levels:
        width = len(str(ramp_levels - 1))
        for j in primaries:
            for i, level in enumerate(ramp_values(ramp_levels)):
                patterns.append(Pattern(f"ramp_{i:0{width}d}{'' if j is None else '_' + j}.png",
                                        "ramp", primary=j, level=level))
    if method == "brute-force":
        width = len(str(gh * gw - 1))
        for k in range(gh * gw):
            patterns += per_primary(f"sp_{k:0{width}d}", "superpixel", index=k)
    elif method == "stripes":
        for r in range(gh):
            patterns += per_primary(f"row_{r:0{len(str(gh - 1))}d}", "row-stripe", band=r)
        for c in range(gw):
            patterns += per_primary(f"col_{c:0{len(str(gw - 1))}d}", "col-stripe", band=c)
    if graycode:
        for axis, size in (("col", gw), ("row", gh)):
            for bit in range(graycode_bits(size)):
                for inverted in (False, True):
                    name = f"gray_{axis}_{bit:02d}{'_inv' if inverted else ''}.png"
                    patterns.append(Pattern(name, "graycode", axis=axis, bit=bit,
                                            inverted=inverted))
    return Manifest(projector, int(superpixel), method, graycode, tuple(patterns), channels,
                    int(ramp_levels))


def write_manifest(folder: Path, manifest: Manifest) -> Path:
    path = Path(folder) / MANIFEST
    with atomic_output(path, "the pattern manifest") as tmp:
        with open(tmp, "w") as f:
            json.dump(manifest.to_dict(), f, indent=1)
            f.write("\n")
    return path


def patterns_folder(patterns) -> Path:
    """The pattern folder of ``patterns`` (the folder, or its manifest file)."""
    path = Path(patterns)
    return path if path.is_dir() else path.parent


def read_manifest(folder) -> Manifest:
    """The manifest of a pattern folder (or the manifest file itself).

    Raises
    ------
    AcquisitionError
        No manifest; one that is not a regular file (a directory, a FIFO nobody writes
        would block the read), larger than :data:`MANIFEST_MAX_BYTES`, not UTF-8 JSON,
        nested past the parser's depth, or not the manifest bigT writes.
    """
    path = Path(folder)
    if path.is_dir():
        path = path / MANIFEST
    text = _manifest_text(path)
    try:
        d = json.loads(text)
    except json.JSONDecodeError as exc:
        raise AcquisitionError(f"the pattern manifest is not JSON ({exc.msg}, line "
                               f"{exc.lineno})", path) from None
    except RecursionError:  # "[[[[...": deeper than the parser's recursion
        raise AcquisitionError("the pattern manifest is not JSON bigT reads (nested too "
                               "deeply)", path) from None
    return Manifest.from_dict(d, path)


#: The largest manifest read: MAX_PATTERNS entries of ~100 bytes (a bigger file, or one
#: that never ends, is refused after this many bytes, not read into memory whole).
MANIFEST_MAX_BYTES = MAX_PATTERNS * 128


def _read_at_most(f, limit: int, chunk: int = 1 << 20) -> bytes:
    """At most ``limit`` bytes of ``f``, read a chunk at a time (``f.read(limit)``
    would allocate the whole limit up front, however small the file)."""
    parts, size = [], 0
    while size < limit:
        part = f.read(min(chunk, limit - size))
        if not part:
            break
        parts.append(part)
        size += len(part)
    return b"".join(parts)


def _manifest_text(path: Path) -> str:
    """The manifest file's text, read only when it is a regular file (``stat`` follows
    a link, which a user may keep to a shared pattern set) and at most
    :data:`MANIFEST_MAX_BYTES` bytes of it."""
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            raise AcquisitionError("the pattern manifest is not a regular file", path)
        with open(path, "rb") as f:
            data = _read_at_most(f, MANIFEST_MAX_BYTES + 1)
    except FileNotFoundError:
        raise AcquisitionError("no pattern manifest here (write one with bigT acquire "
                               "patterns)", path) from None
    except OSError as exc:
        raise AcquisitionError(f"cannot read the pattern manifest ({exc.strerror or exc})",
                               path) from None
    if len(data) > MANIFEST_MAX_BYTES:
        raise AcquisitionError(f"the pattern manifest is larger than {MANIFEST_MAX_BYTES} "
                               "bytes, more than any pattern set bigT writes", path)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise AcquisitionError("the pattern manifest is not JSON (not UTF-8 text)",
                               path) from None
