"""Which files of a captures folder hold which pattern, at which exposure time.

Two layouts (docs/CALIBRATION.md "Capturing"), one per folder:

* *single exposure*: ``<pattern>.<ext>``, one capture per pattern (``white.png``);
* *exposure brackets*: ``<pattern>@<exposure>.<ext>``, several captures per pattern,
  each ``<exposure>`` its exposure time in seconds, written as a decimal number
  (``white@0.004.png``, ``white@2.5.tif``, ``1e-3``) or as a fraction with ``-`` for
  ``/`` (``white@1-250.dng``: 1/250 s; a trailing ``s`` is allowed), or any other label
  (``white@a.tif``) when the file's EXIF records the time. A time in the name and one
  in the EXIF must agree within :data:`EXIF_TOLERANCE`; every pattern must be captured
  at every exposure time any pattern has (the bracket is set once on the camera).

A bracket's captures are in rising order: by their times when every name gives one,
else by their labels (digits compared as numbers), the times then checked to rise.
RAW camera files (:data:`RAW_SUFFIXES`, read by :func:`bigT.calibration.read_raw`) are
linear already.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

from ..errors import AcquisitionError

#: Marks a bracketed capture's exposure in its file name: ``white@0.01.png``.
MARK = "@"
#: RAW camera files: read through rawpy (optional), linear.
RAW_SUFFIXES = (".dng", ".cr2", ".cr3", ".nef", ".arw", ".orf", ".rw2", ".raf", ".pef", ".srw")
#: File types whose EXIF is read for the exposure time (Pillow opens them).
EXIF_SUFFIXES = (".tif", ".tiff", ".png")
#: Largest relative difference between a name's exposure time and the EXIF's
#: (a camera's 1/3 s is 0.333 s, written 0.33 in a name: 1 %).
EXIF_TOLERANCE = 0.02
_DECIMAL = re.compile(r"^(\d+(\.\d*)?|\.\d+)([eE][-+]?\d+)?s?$")
_FRACTION = re.compile(r"^(\d+(\.\d*)?)-(\d+(\.\d*)?)s?$")


@dataclass(frozen=True)
class Shot:
    """One capture of a bracket.

    Attributes
    ----------
    path : Path of the file
    seconds : float, its exposure time
    """

    path: Path
    seconds: float

    @property
    def raw(self) -> bool:
        """A RAW camera file (linear: no camera response applied)."""
        return self.path.suffix.lower() in RAW_SUFFIXES


@dataclass(frozen=True)
class Bracket:
    """The captures of one pattern, shortest exposure first.

    Attributes
    ----------
    pattern : str, the pattern's stem
    shots : tuple of Shot (one, without a time, in the single-exposure layout)
    """

    pattern: str
    shots: tuple[Shot, ...]

    @property
    def times(self) -> tuple[float, ...]:
        return tuple(s.seconds for s in self.shots)

    @property
    def paths(self) -> tuple[Path, ...]:
        return tuple(s.path for s in self.shots)


def split_name(path: Path) -> tuple[str, str | None]:
    """``(pattern stem, exposure label)`` of a capture file; the label is None in the
    single-exposure layout (no ``@``)."""
    stem, mark, label = path.stem.partition(MARK)
    return (stem, label) if mark else (stem, None)


def seconds_in_label(label: str) -> float | None:
    """The exposure time a label spells (``0.004``, ``1e-3``, ``1-250``, ``2.5s``), or
    None when it spells none (``a``, ``e1``)."""
    text = label.strip()
    if _DECIMAL.match(text):
        value = float(text.rstrip("sS"))
    elif _FRACTION.match(text):
        top, _, bottom = text.rstrip("sS").partition("-")
        value = float(top) / float(bottom) if float(bottom) else 0.0
    else:
        return None
    # 1e999 or 400 digits spell no time a camera takes (inf), 1e-999 none (0)
    return value if 0 < value < math.inf else None


def seconds_text(t: float) -> str:
    """``1/250 s`` under a second, ``2.5 s`` above."""
    return f"1/{1 / t:.4g} s" if t < 1 else f"{t:.4g} s"


def _natural(label: str):
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", label)]


def _exif_seconds(path: Path) -> float | None:
    if path.suffix.lower() not in EXIF_SUFFIXES:
        return None
    from ..calibration import exposure_time_from_exif

    return exposure_time_from_exif(path)


def _shot(path: Path, label: str, pattern: str, folder: Path) -> Shot:
    named, exif = seconds_in_label(label), _exif_seconds(path)
    if named is None and exif is None:
        raise AcquisitionError(
            f"bracket of pattern {pattern!r}: {path.name} has no exposure time (name it "
            f"{pattern}{MARK}<seconds>{path.suffix}, e.g. {pattern}{MARK}0.004{path.suffix} "
            f"or {pattern}{MARK}1-250{path.suffix}, or keep the camera's EXIF)", folder)
    if named is not None and exif is not None and abs(named - exif) > EXIF_TOLERANCE * exif:
        raise AcquisitionError(
            f"bracket of pattern {pattern!r}: {path.name} says {seconds_text(named)} but its "
            f"EXIF {seconds_text(exif)}; rename it", folder)
    return Shot(path, named if named is not None else exif)


def bracket(pattern: str, labelled: list[tuple[Path, str]], folder: Path) -> Bracket:
    """The bracket of ``pattern`` from its files and their labels, in rising order
    (module docstring); its times not yet checked to rise (``check_bracket`` does)."""
    by_name = all(seconds_in_label(label) is not None for _, label in labelled)
    ordered = sorted(labelled, key=lambda pl: (seconds_in_label(pl[1]),) if by_name
                     else (_natural(pl[1]),))
    shots = tuple(_shot(path, label, pattern, folder) for path, label in ordered)
    for before, after in zip(shots, shots[1:]):
        if after.seconds <= before.seconds:
            same = "the same as" if after.seconds == before.seconds else "after"
            raise AcquisitionError(
                f"bracket of pattern {pattern!r}: exposures out of order: "
                f"{seconds_text(after.seconds)} ({after.path.name}) {same} "
                f"{seconds_text(before.seconds)} ({before.path.name}); they must rise "
                "strictly in the labels' order", folder)
    return Bracket(pattern, shots)


def check_same_exposures(brackets: dict[str, Bracket], folder: Path) -> tuple[float, ...]:
    """Every pattern captured at every exposure time some pattern has: the times of
    the bracket, rising; AcquisitionError naming the first pattern that lacks one."""
    every = sorted({t for b in brackets.values() for t in b.times})
    for b in brackets.values():
        missing = [t for t in every if not any(_same(t, s) for s in b.times)]
        if missing:
            raise AcquisitionError(
                f"bracket of pattern {b.pattern!r}: no capture at "
                f"{', '.join(seconds_text(t) for t in missing)}, which other patterns have "
                f"(an exposure is missing; its exposures: "
                f"{', '.join(seconds_text(t) for t in sorted(b.times))})", folder)
    return tuple(every)


def _same(a: float, b: float) -> bool:
    return abs(a - b) <= 1e-9 * max(a, b)
