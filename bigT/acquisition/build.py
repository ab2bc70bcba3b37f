"""From captures to T: ``bigT acquire build`` (:func:`build_transport`).

The steps, each reading one capture at a time:

1. the black level, the white capture's signal (all black: refused), the camera's pixel
   noise (robust, from neighbour differences of the black capture, with the
   quantisation's) and the noise floor of T's entries, row by row (3 sigma of the mean of
   the row's camera super-pixel, so a small group gets a higher floor);
2. the correspondence (:mod:`.correspondence`): Gray code when the pattern set has it,
   else each camera pixel's maximum response;
3. T, tile row by tile row. A pass streams the captures and keeps, for the tile rows it
   fills, the camera super-pixel means at or above the floor; when those entries
   outgrow the memory budget the pass gives back its last half of tile rows to a later
   pass (CombBLAS's "phases", by rows), down to one tile row (a tile row alone over the
   budget is gathered whole, with one MemoryLimitWarning). Brute force: column p of T is
   the capture of super-pixel p. Stripes (Ding et al. 2009): the response to
   super-pixel (r, c) is the element-wise minimum of the responses to row stripe r and
   column stripe c, which holds the direct light of (r, c) and over-estimates the rest
   (both stripes' light reaches a pixel; the smaller is still more than (r, c)'s share).

Colour (a pattern set of ``channels: 3``): T is 3 n x 3 n, column 3 q + j the capture of
primary j lit on super-pixel q (less the black level), row 3 p + i camera channel i of
camera super-pixel p, each row with the floor of its own channel's noise; stripes take
the minimum primary by primary. A ``--mixing`` file's global 3x3 mixing is recorded in
T's metadata (:mod:`.mixing`).

A tile row is written whole by :class:`bigT.BlockCSRWriter` and only then marked done,
so an interrupted build resumes with the tile rows not yet written -- when the settings
and the capture files (names, sizes, modification times) are the same.
"""

from __future__ import annotations

import json
import shutil
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from .. import config
from ..atomic import atomic_output, refuse_overwriting_inputs
# what build stores beside T is read by compensation too, so its reader lives there
from ..compensation.rig import (ACQUISITION_KEY, CORRESPONDENCE,
                                load_correspondence)  # noqa: F401 (acquisition's API)
from ..errors import AcquisitionError, MemoryLimitWarning, StoreError
from ..progress import progress_bar
from ..storage import (BlockCSRWriter, PixelOrder, check_replaceable, is_url, move_into_place,
                       read_store_attrs, temporary_sibling)
from ..storage import open as open_store
from ..calibration import CameraResponse, ProjectorResponse, parse_camera_response
from .brackets import seconds_text
from .captures import Captures, grey_view
from .correspondence import Correspondence, GroupMeans, from_graycode, from_maximum_response
from .manifest import Manifest, patterns_folder, read_manifest
from .mixing import MIXING_KEY, Mixing, read_mixing
from .ramp import PROJECTOR_RESPONSE_FILE, PROJECTOR_RESPONSE_KEY, fit_ramp, save_response

#: The camera response a build applied, kept beside the correspondence (JSON,
#: ``CameraResponse.save``): a recovered one is measured once.
CAMERA_RESPONSE = "camera_response.json"

class AcquisitionWarning(UserWarning):
    """Something in the captures that makes T less accurate (saturated pixels)."""


@dataclass(frozen=True)
class BuildSettings:
    """How captures became T; recorded in the store's metadata[\"acquisition\"] and
    compared when an interrupted build resumes.

    Attributes
    ----------
    floor : float
        The highest floor of any row: ``--floor``, or by default that of the smallest
        camera super-pixel (every entry kept is at least its row's floor).
    floor_min : float, the lowest floor of any row (``floor`` with ``--floor``)
    pixel_noise : float, a camera pixel's noise as estimated (quantisation not added;
        of colour captures, their grey view's)
    capture_files : str, a hash of the capture files' names, sizes and modification times
    channels : {1, 3}, grey or colour (recorded for colour only)
    channel_noise : (float, float, float) or None, the noise of each camera channel of
        colour captures, as ``pixel_noise`` (recorded for colour only)
    """

    patterns: str
    captures: str
    method: str
    projector: tuple[int, int]
    superpixel: int
    camera: tuple[int, int]
    gamma: float
    black: str | None
    floor: float
    pixel_noise: float
    correspondence: str
    floor_min: float
    capture_files: str
    channels: int = 1
    channel_noise: tuple[float, ...] | None = None
    camera_response: str | None = None
    exposures: tuple[float, ...] | None = None
    ramp_levels: int = 0

    def to_dict(self) -> dict:
        """JSON-serialisable; a build of single exposures, no ``--camera-response`` and
        no ramp (grey) has the keys it always had."""
        d = dict(self.__dict__)
        d["projector"], d["camera"] = list(self.projector), list(self.camera)
        if self.channels == 1:
            del d["channels"], d["channel_noise"]
        else:
            d["channel_noise"] = list(self.channel_noise)
        for key in ("camera_response", "exposures"):
            if d[key] is None:
                del d[key]
        if self.exposures is not None:
            d["exposures"] = list(self.exposures)
        if not self.ramp_levels:
            del d["ramp_levels"]
        return d


@dataclass(frozen=True)
class BuildReport:
    """What ``bigT acquire build`` did.

    Attributes
    ----------
    path : Path of the T store
    settings : BuildSettings
    n : int, side of T (projector super-pixels, times 3 for colour)
    seen : int, super-pixels with a camera super-pixel; the others are left out
    nnz : int, stored entries of T
    passes : int, passes over the captures that filled tile rows (0: all were done)
    saturated_pixels : int, pixels at full scale over all captures read
    seconds : float
    black_level : float, mean of the black level subtracted (the black capture's or
        ``--black``'s)
    mixing : Mixing or None, the global colour mixing recorded in T's metadata
    projector_response : ProjectorResponse or None, fitted from the ramp and kept in
        the store (``projector_response.json``); None without a ramp
    camera : str, the camera response applied, in words
    """

    path: Path
    settings: BuildSettings
    n: int
    seen: int
    nnz: int
    passes: int
    saturated_pixels: int
    seconds: float
    black_level: float = 0.0
    mixing: Mixing | None = None
    projector_response: ProjectorResponse | None = None
    camera: str = "linear"

    @property
    def superpixels(self) -> int:
        """Projector super-pixels (T's side over the channels)."""
        return self.n // self.settings.channels

    def describe(self) -> str:
        s = self.settings
        colour = "" if s.channels == 1 else "colour, R G B per super-pixel; "
        noise = (f"{s.pixel_noise:.3g} per camera pixel" if s.channels == 1 else
                 "R {:.3g}, G {:.3g}, B {:.3g} per camera pixel".format(*s.channel_noise))
        lines = [
            f"T from {s.method} captures: {self.n} x {self.n} "
            f"({colour}{s.projector[0]}x{s.projector[1]} projector, {s.superpixel}x"
            f"{s.superpixel} super-pixels; camera {s.camera[0]}x{s.camera[1]})",
            f"correspondence: {s.correspondence}; {self.seen} of {self.superpixels} "
            f"super-pixels seen, {self.superpixels - self.seen} left out",
            f"black level {self.black_level:.3g} (from "
            f"{'--black ' + Path(s.black).name if s.black else 'the black capture'}); "
            f"noise: {noise}; floor "
            + (f"{s.floor:.3g}" if s.floor_min == s.floor else
               f"{s.floor_min:.3g} to {s.floor:.3g} (by camera super-pixel size)")
            + f"; {self.nnz} entries ({self.nnz / max(self.n, 1):.1f} per row)",
            f"{self.passes} pass(es) over the captures, {self.seconds:.1f} s"
            + (f"; {self.saturated_pixels} saturated pixels" if self.saturated_pixels else ""),
        ]
        if s.exposures is not None or s.camera_response is not None:
            lines.append(f"camera response: {self.camera}"
                         + ("" if s.exposures is None else
                            f"; brackets of {len(s.exposures)} exposures ("
                            + ", ".join(seconds_text(t) for t in s.exposures)
                            + ") merged into linear radiance"))
        r = self.projector_response
        if r is None:
            lines.append("projector response: none measured (no ramp in the patterns): "
                         "the projector is taken as linear")
        else:
            blacks = ", ".join(f"{c} {b:.3g}" for c, b in zip(r.channels, r.black))
            lines.append(f"projector response: fitted from a ramp of {len(r.levels)} levels"
                         f"{' per primary' if r.n_channels == 3 else ''} (black {blacks}; "
                         f"light above black), kept in the store as "
                         f"{PROJECTOR_RESPONSE_FILE}")
        if self.mixing is not None:
            lines.append(f"global colour mixing recorded in T's metadata ({MIXING_KEY}): "
                         f"{self.mixing.describe()}")
        return "\n".join(lines)


def build_transport(patterns, captures, output, *, black=None, floor: float | None = None,
                    gamma: float = 1.0, tile_size: int | None = None,
                    pixel_order: str = "tile-major", memory_bytes: int | None = None,
                    overwrite: bool = False, progress: bool | None = None,
                    mixing=None, camera_response=None) -> BuildReport:
    """Assemble T from a pattern folder and its captures into a bigT store.

    Parameters
    ----------
    patterns : path of the folder written by ``bigT acquire patterns``
    captures : path of the folder holding one capture per pattern
    output : path of the T store to write (resumed when an interrupted build of the
        same captures left it)
    black : path, optional, a black-level image instead of the black pattern's capture
        (values on the captures' scale)
    floor : float, optional
        Entries of T below it are dropped. Default: per row, ``config.ACQUIRE_FLOOR_SIGMAS``
        times the noise of the row's camera super-pixel, sqrt(2 (sigma^2 + q^2/12) /
        count) for a group of ``count`` camera pixels of noise sigma and quantum q.
    gamma : float, the camera's gamma (captures are raised to it)
    tile_size, pixel_order : the store's layout
    memory_bytes : budget for the entries gathered in one pass
    overwrite : replace a complete store (or an interrupted one of other captures)
    mixing : path of a JSON file ``{"camera": 3x3, "projector": 3x3}``, or a
        :class:`Mixing`, optional
        The rig's global colour mixing (colour pattern sets only), recorded in T's
        metadata as ``mixing`` for the engine's global path.
    camera_response : CameraResponse or str, optional
        The camera's response (``linear``, ``srgb``, ``gamma:G``, a table file,
        ``recover`` or ``recover:robertson``; :class:`Captures`); default ``gamma``'s.
        Applied to single exposures and to each exposure of a bracket before the merge.

    Returns
    -------
    BuildReport

    Notes
    -----
    A build into ``output`` that is interrupted resumes when run again with the same
    settings and capture files; with other ones it is refused (naming what differs)
    unless ``overwrite``. An ``overwrite`` build of an *existing* store is not
    resumable: it builds in a hidden sibling, so that the old store stays whole until
    the new one is, and an interrupted or failed one is removed; run again, it starts
    over.
    """
    t0 = time.perf_counter()
    if is_url(output):  # refused before anything is read, never a local "s3:" folder
        raise AcquisitionError("a measured T is built on the machine that holds the "
                               "captures: give a directory, then put the store in the "
                               "bucket (bigT.storage.upload_tree)", str(output))
    refuse_overwriting_inputs([output], [patterns, captures, black])
    manifest = read_manifest(patterns)
    mixing = _checked_mixing(mixing, manifest)
    if manifest.method == "graycode":
        raise AcquisitionError(
            "Gray-code patterns give the correspondence, not T: acquire T with "
            "{option} or stripes (add Gray code for the correspondence)",
            Path(patterns), option=("method", "brute-force"))
    if Path(captures).resolve() == patterns_folder(patterns).resolve():
        # the patterns have the captures' names: they would be read as the captures
        raise AcquisitionError(
            "the captures folder is the pattern folder: put the camera's captures in a "
            "folder of their own", Path(captures))
    cap = Captures(manifest, Path(captures), gamma=gamma, black_file=black and Path(black),
                   camera_response=camera_response)
    white = grey_view(cap.signal(manifest.single("white")))  # geometry: the grey view
    noise = cap.pixel_noise()
    if white.max() <= 2 * cap.pixel_floor() + 1e-12:  # no pixel clearly above the noise
        raise AcquisitionError("the captures are all black: the white pattern's capture is "
                               "no brighter than the black one (projector off? lens cap?)",
                               cap.path(manifest.single("white")))
    bar = _bar(progress)
    corr = _correspondence(manifest, cap, white, bar)
    order = PixelOrder(manifest.grid, pixel_order, channels=manifest.channels)
    means = corr.reducer(order)
    if not means.seen.any():
        raise AcquisitionError("no camera pixel is lit directly by any super-pixel: is the "
                               "camera looking at the projected area?", Path(captures))
    # fitted before the store is touched: a bad ramp leaves what exists as it was
    response = fit_ramp(manifest, cap, corr) if manifest.ramp_levels else None
    if floor is None:
        # row 3 p + i (p + 0 for grey) has camera channel i's noise
        row_noise = np.tile(cap.channel_noise(), order.pixels)
        floors = superpixel_noise(row_noise, means.counts) * config.ACQUIRE_FLOOR_SIGMAS
    else:
        floors = np.full(order.n, float(floor))
    channel_noise = (None if manifest.channels == 1 else
                     tuple(cap.pixel_noise(c) for c in range(manifest.channels)))
    settings = BuildSettings(
        str(Path(patterns).resolve()), str(Path(captures).resolve()), manifest.method,
        manifest.projector, manifest.superpixel, cap.shape, float(gamma),
        str(Path(black).resolve()) if black else None, float(floors[means.seen].max()),
        noise, corr.source, float(floors[means.seen].min()), cap.fingerprint(),
        manifest.channels, channel_noise,
        _camera_spec(camera_response), cap.exposures,
        manifest.ramp_levels)
    target = Path(output)
    # with overwrite, an existing store is replaced only by a complete one: a bad capture
    # first read while filling (Gray code reads T's captures only then) or an interrupt
    # leaves it as it was
    aside = overwrite and target.exists()
    if aside:
        check_replaceable(target, True)
    where = temporary_sibling(target) if aside else target
    try:
        writer = _open_writer(where, order, settings, mixing, tile_size,
                              overwrite and not aside, response is not None)
        _save_correspondence(writer.path, corr)
        if response is not None:  # in the store before it is complete
            save_response(writer.path, response)
        if camera_response is not None:  # what check_white and a reader undo again
            cap.response.save(writer.path / ACQUISITION_KEY / CAMERA_RESPONSE)
        passes = _fill(writer, manifest, cap, means, floors,
                       memory_bytes or config.ACQUIRE_MEMORY_BYTES, progress)
        T = writer.finalize()
        if aside:
            move_into_place(where, target)
            T = open_store(target)
    except BaseException:
        if aside:
            shutil.rmtree(where, ignore_errors=True)
        raise
    warning = cap.saturation_warning()
    if warning:
        warnings.warn(warning, AcquisitionWarning, stacklevel=2)
    return BuildReport(T.path, settings, order.n, means.seen_superpixels, int(T.nnz), passes,
                       sum(cap.saturated.values()), time.perf_counter() - t0,
                       float(cap.black.mean()), mixing, response, cap.response.describe())


def _checked_mixing(mixing, manifest: Manifest) -> Mixing | None:
    """``mixing`` (a file or a Mixing) read, for a colour pattern set only."""
    if mixing is None:
        return None
    if manifest.channels == 1:
        raise AcquisitionError("a colour mixing ({option}) is for a colour pattern set; these "
                               "patterns are grey (write them in colour, 3 channels)",
                               mixing if not isinstance(mixing, Mixing) else None,
                               option="mixing")
    return mixing if isinstance(mixing, Mixing) else read_mixing(mixing)


def superpixel_noise(pixel_noise, counts: np.ndarray) -> np.ndarray:
    """Noise std of each camera super-pixel: a pixel's signal holds the noise of its
    capture and of the black capture (sqrt 2), averaged over the group's own ``counts``
    pixels (a group of 4 pixels is twice as noisy as one of 16, so one floor for all
    would keep the small groups' noise and drop the large groups' light).

    ``pixel_noise``: a float, or an array of counts' shape (each row's channel's).

    Returns
    -------
    ndarray, shape counts.shape, float64: inf for an empty group (nothing measured)
    """
    counts = np.asarray(counts)
    safe = np.maximum(counts, 1)
    return np.where(counts > 0, pixel_noise * np.sqrt(2.0 / safe), np.inf)


def _bar(progress):
    def wrap(items, desc="captures"):
        return progress_bar(items, progress=progress, desc=desc, unit="image")
    return wrap


def _correspondence(manifest, cap, white, bar) -> Correspondence:
    if manifest.graycode:
        return from_graycode(manifest, cap)
    # a colour place's response sums its three primaries' captures
    return from_maximum_response(manifest, cap, white, cap.pixel_floor(summed=manifest.channels),
                                 progress=lambda it: bar(it, "correspondence"))


def _open_writer(path: Path, order: PixelOrder, settings: BuildSettings,
                 mixing: Mixing | None, tile_size, overwrite: bool,
                 with_response: bool = False) -> BlockCSRWriter:
    """A new store, or the interrupted build of the same settings (and mixing) resumed
    (refused, naming the settings that differ, when they are not the same).
    ``with_response``: the store keeps a projector response, named in its metadata."""
    meta = {ACQUISITION_KEY: settings.to_dict()}
    if mixing is not None:
        meta[MIXING_KEY] = mixing.to_metadata()
    if with_response:
        meta[PROJECTOR_RESPONSE_KEY] = PROJECTOR_RESPONSE_FILE
    shape = (order.n, order.n)
    if path.exists() and not overwrite:
        try:
            old = read_store_attrs(path)
        except StoreError:
            old = None
        if old is not None and not old.complete:
            differ = _differing(old.metadata.get(ACQUISITION_KEY),
                                json.loads(json.dumps(meta[ACQUISITION_KEY])))
            if old.metadata.get(MIXING_KEY) != meta.get(MIXING_KEY):
                differ.append(MIXING_KEY)
            if differ:
                raise AcquisitionError(
                    f"holds an interrupted build of other captures or settings "
                    f"({', '.join(differ)} differ); pass {{option}} to start again", path,
                    option=("overwrite", True))
            return BlockCSRWriter(path, shape, tile_size=old.tile_size, pixel_order=order,
                                  metadata=meta, resume=True)
    return BlockCSRWriter(path, shape, tile_size=tile_size, pixel_order=order, metadata=meta,
                          overwrite=overwrite)


def _differing(old, new: dict) -> list[str]:
    """The keys of the settings ``new`` whose values ``old`` does not share (all of them
    when ``old`` records none)."""
    if not isinstance(old, dict):
        return sorted(new)
    return sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))


def _save_correspondence(store: Path, corr: Correspondence) -> None:
    """The camera pixel -> super-pixel map, ``STORE/acquisition/correspondence.npy``
    ((Hc, Wc) int32, -1 outside every group), next to the tiles."""
    folder = store / ACQUISITION_KEY
    folder.mkdir(exist_ok=True)
    with atomic_output(folder / CORRESPONDENCE, "the correspondence map") as tmp:
        with open(tmp, "wb") as f:
            np.save(f, corr.labels.astype(np.int32))


def _camera_spec(spec) -> str | None:
    """``--camera-response`` as recorded in the settings: a file by its absolute path,
    a CameraResponse by its description, None when not given."""
    if spec is None:
        return None
    if isinstance(spec, CameraResponse):
        return spec.describe()
    text = str(spec).strip()
    return str(Path(text).resolve()) if text.lower().endswith((".npy", ".json")) else text


def load_camera_response(store) -> CameraResponse | None:
    """The camera response a build applied (``--camera-response``), kept in the store as
    ``acquisition/camera_response.json``; None when the build had none (``gamma``)."""
    path = Path(store) / ACQUISITION_KEY / CAMERA_RESPONSE
    return parse_camera_response(str(path)) if path.is_file() else None


# --- filling the tile rows ---------------------------------------------------------

def _fill(writer: BlockCSRWriter, manifest: Manifest, cap: Captures, means: GroupMeans,
          floors: np.ndarray, budget: int, progress) -> int:
    """Write every missing tile row; returns the number of passes over the captures.

    ``floors`` : (n,) the floor of each row of T (matrix order)."""
    column = _column_of(writer.pixel_order, means.seen)
    gather = _gather_stripes if manifest.method == "stripes" else _gather_brute_force
    limit = _Budget(budget)
    passes = 0
    missing = writer.missing_tile_rows
    while missing:
        rows = _Rows(writer, missing)
        entries = gather(rows, manifest, cap, means, floors, limit, column, progress)
        rows.write(*entries.arrays(), writer.shape[1])
        missing = [i for i in missing if i not in rows.tiles]
        passes += 1
    return passes


def _column_of(order: PixelOrder, seen_matrix: np.ndarray) -> np.ndarray:
    """(pixels, channels) int64: [grid index, primary] -> matrix column; -1 for unseen
    super-pixels (left out)."""
    # the row-major value index of (g, j) is channels g + j
    col = order.inverse_permutation.reshape(order.pixels, order.channels).copy()
    col[~seen_matrix[col]] = -1
    return col


class _Rows:
    """The tile rows one pass fills, and the matrix rows they hold."""

    def __init__(self, writer: BlockCSRWriter, tiles: list[int]):
        self.writer, self.tiles = writer, list(tiles)
        self.mask = np.zeros(writer.shape[0], dtype=bool)
        for i in self.tiles:
            a, b = writer.tile_row_range(i)
            self.mask[a:b] = True

    def give_back_half(self) -> None:
        """Keep the first half of the tile rows (at least one)."""
        keep = max(1, len(self.tiles) // 2)
        for i in self.tiles[keep:]:
            a, b = self.writer.tile_row_range(i)
            self.mask[a:b] = False
        self.tiles = self.tiles[:keep]

    def write(self, rows, cols, vals, n: int) -> None:
        """Write each tile row of the pass from its COO entries (global indices)."""
        order = np.argsort(rows, kind="stable")
        rows, cols, vals = rows[order], cols[order], vals[order]
        for i in self.tiles:
            a, b = self.writer.tile_row_range(i)
            lo, hi = np.searchsorted(rows, [a, b])
            block = sp.csr_array((vals[lo:hi], (rows[lo:hi] - a, cols[lo:hi])), shape=(b - a, n))
            self.writer.write_tile_row(i, block)


class _Budget:
    """The bytes one pass may gather, shared by the passes of a build."""

    def __init__(self, nbytes: int):
        self.nbytes = int(nbytes)
        self.warned = False

    def fit(self, rows: "_Rows", entries: "_Entries", reserved: int = 0) -> None:
        """Give back half of the pass's tile rows (and their entries) while the entries
        and ``reserved`` bytes outgrow the budget; a single tile row is kept whatever it
        holds (a tile row is written whole), with one warning per build."""
        while entries.nbytes + reserved > self.nbytes and len(rows.tiles) > 1:
            rows.give_back_half()
            entries.keep_rows(rows.mask)
        if entries.nbytes + reserved > self.nbytes and not self.warned:
            self.warned = True
            warnings.warn(MemoryLimitWarning(
                f"tile row {rows.tiles[0]} of T alone holds more entries than the memory "
                f"limit of {self.nbytes} bytes for one pass; it is gathered whole (a "
                "smaller tile size or a larger memory limit keeps to the limit)"),
                stacklevel=2)


class _Entries:
    """COO entries gathered by a pass, with their bytes (12 per entry as CSR + 8 here)."""

    def __init__(self):
        self.parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self.count = 0

    @property
    def nbytes(self) -> int:
        return 20 * self.count

    def add(self, rows, cols, vals) -> None:
        self.parts.append((rows, cols, vals))
        self.count += len(rows)

    def keep_rows(self, mask: np.ndarray) -> None:
        self.parts = [(r[mask[r]], c[mask[r]], v[mask[r]]) for r, c, v in self.parts]
        self.count = sum(len(r) for r, _, _ in self.parts)

    def arrays(self):
        if not self.parts:
            e = np.zeros(0, np.int64)
            return e, e, np.zeros(0)
        return tuple(np.concatenate(x) for x in zip(*self.parts))


def _gather_brute_force(rows: _Rows, manifest: Manifest, cap: Captures, means: GroupMeans,
                        floors: np.ndarray, budget: _Budget, column: np.ndarray,
                        progress) -> _Entries:
    """One pass of brute force: column q of T is the capture of super-pixel q (3 q + j:
    of super-pixel q lit in primary j)."""
    entries = _Entries()
    for p in progress_bar(manifest.of_kind("superpixel"), progress=progress, desc="T columns",
                          unit="image"):
        col = column[p.index, p.primary_index]
        if col < 0:
            continue  # unseen super-pixel: its column is left out
        y = means(cap.signal(p))
        r = np.flatnonzero((y >= floors) & (y > 0) & rows.mask)  # noise may be negative
        entries.add(r, np.full(len(r), col, dtype=np.int64), y[r])
        budget.fit(rows, entries)
    return entries


def _gather_stripes(rows: _Rows, manifest: Manifest, cap: Captures, means: GroupMeans,
                    floors: np.ndarray, budget: _Budget, column: np.ndarray,
                    progress) -> _Entries:
    """One pass of stripes: row q of T at super-pixel (r, c) is min(H[q, r], V[q, c]),
    H and V row q's responses to the row and column stripes (of colour: primary by
    primary, the stripes of primary j giving column 3 (r, c) + j). The responses of
    the pass's rows are held first; the entries they make (up to n a row) count
    against the budget with them as they are made."""
    gh, gw = manifest.grid
    primaries = column.shape[1]
    response_bytes = 8 * (gh + gw) * primaries  # a row of H and V
    while rows.mask.sum() * response_bytes > budget.nbytes and len(rows.tiles) > 1:
        rows.give_back_half()
    index = np.flatnonzero(rows.mask)
    H = np.zeros((len(index), gh, primaries))
    V = np.zeros((len(index), gw, primaries))
    stripes = manifest.of_kind("row-stripe") + manifest.of_kind("col-stripe")
    for p in progress_bar(stripes, progress=progress, desc="stripes", unit="image"):
        y = means(cap.signal(p))[index]
        (H if p.kind == "row-stripe" else V)[:, p.band, p.primary_index] = y
    reserved = H.nbytes + V.nbytes
    entries = _Entries()
    for k, q in enumerate(index):
        if not rows.mask[q]:
            continue  # its tile row was given back to a later pass
        floor = floors[q]
        for j in range(primaries):
            h, v = H[k, :, j], V[k, :, j]
            r = np.flatnonzero((h >= floor) & (h > 0))
            c = np.flatnonzero((v >= floor) & (v > 0))
            vals = np.minimum.outer(h[r], v[c]).ravel()
            cols = column[(r[:, None] * gw + c[None, :]).ravel(), j]
            keep = (vals >= floor) & (cols >= 0)
            entries.add(np.full(int(keep.sum()), q, dtype=np.int64), cols[keep], vals[keep])
        budget.fit(rows, entries, reserved)
    return entries
