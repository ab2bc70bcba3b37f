"""From captures to T: ``bigT acquire build`` (:func:`build_transport`).

The steps, each reading one capture at a time:

1. the black level, the white capture's signal (all black: refused), the camera's pixel
   noise (robust, from the black capture) and the noise floor of T's entries;
2. the correspondence (:mod:`.correspondence`): Gray code when the pattern set has it,
   else each camera pixel's maximum response;
3. T, tile row by tile row. A pass streams the captures and keeps, for the tile rows it
   fills, the camera super-pixel means at or above the floor; when those entries
   outgrow the memory budget the pass gives back its last tile rows to a later pass
   (CombBLAS's "phases", by rows). Brute force: column p of T is the capture of
   super-pixel p. Stripes (Ding et al. 2009): the response to super-pixel (r, c) is the
   element-wise minimum of the responses to row stripe r and column stripe c, which
   holds the direct light of (r, c) and over-estimates the rest (both stripes' light
   reaches a pixel; the smaller is still more than (r, c)'s share).

A tile row is written whole by :class:`bigT.BlockCSRWriter` and only then marked done,
so an interrupted build resumes with the tile rows not yet written.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from .. import config
from ..errors import AcquisitionError, StoreError
from ..progress import progress_bar
from ..storage import BlockCSRWriter, PixelOrder
from ..storage import open as open_store
from ..storage.writer import (check_replaceable, move_into_place, read_store_attrs,
                              temporary_sibling)
from .captures import Captures
from .correspondence import Correspondence, GroupMeans, from_graycode, from_maximum_response
from .manifest import Manifest, read_manifest

ACQUISITION_KEY = "acquisition"
CORRESPONDENCE = "correspondence.npy"


@dataclass(frozen=True)
class BuildSettings:
    """How captures became T; recorded in the store's metadata[\"acquisition\"] and
    compared when an interrupted build resumes."""

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

    def to_dict(self) -> dict:
        d = dict(self.__dict__)
        d["projector"], d["camera"] = list(self.projector), list(self.camera)
        return d


@dataclass(frozen=True)
class BuildReport:
    """What ``bigT acquire build`` did.

    Attributes
    ----------
    path : Path of the T store
    settings : BuildSettings
    n : int, side of T (projector super-pixels)
    seen : int, super-pixels with a camera super-pixel; n - seen are left out
    nnz : int, stored entries of T
    passes : int, passes over the captures that filled tile rows (0: all were done)
    saturated_pixels : int, pixels at full scale over all captures read
    seconds : float
    """

    path: Path
    settings: BuildSettings
    n: int
    seen: int
    nnz: int
    passes: int
    saturated_pixels: int
    seconds: float

    def describe(self) -> str:
        s = self.settings
        return "\n".join([
            f"T from {s.method} captures: {self.n} x {self.n} "
            f"({s.projector[0]}x{s.projector[1]} projector, {s.superpixel}x{s.superpixel} "
            f"super-pixels; camera {s.camera[0]}x{s.camera[1]})",
            f"correspondence: {s.correspondence}; {self.seen} of {self.n} super-pixels seen, "
            f"{self.n - self.seen} left out",
            f"noise: {s.pixel_noise:.3g} per camera pixel; floor {s.floor:.3g}; "
            f"{self.nnz} entries ({self.nnz / max(self.n, 1):.1f} per row)",
            f"{self.passes} pass(es) over the captures, {self.seconds:.1f} s"
            + (f"; {self.saturated_pixels} saturated pixels" if self.saturated_pixels else ""),
        ])


def build_transport(patterns, captures, output, *, black=None, floor: float | None = None,
                    gamma: float = 1.0, tile_size: int | None = None,
                    pixel_order: str = "tile-major", memory_bytes: int | None = None,
                    overwrite: bool = False, progress: bool | None = None) -> BuildReport:
    """Assemble T from a pattern folder and its captures into a bigT store.

    Parameters
    ----------
    patterns : path of the folder written by ``bigT acquire patterns``
    captures : path of the folder holding one capture per pattern
    output : path of the T store to write (resumed when an interrupted build of the
        same captures left it)
    black : path, optional, a black-level image instead of the black pattern's capture
    floor : float, optional
        Entries of T below it are dropped. Default ``config.ACQUIRE_FLOOR_SIGMAS`` times
        the noise of a camera super-pixel.
    gamma : float, the camera's gamma (captures are raised to it)
    tile_size, pixel_order : the store's layout
    memory_bytes : budget for the entries gathered in one pass
    overwrite : replace a complete store (or an interrupted one of other captures)

    Returns
    -------
    BuildReport
    """
    t0 = time.perf_counter()
    manifest = read_manifest(patterns)
    if manifest.method == "graycode":
        raise AcquisitionError(
            "Gray-code patterns give the correspondence, not T: acquire T with "
            "--method brute-force or stripes (add --graycode for the correspondence)",
            Path(patterns))
    cap = Captures(manifest, Path(captures), gamma=gamma, black_file=black and Path(black))
    white = cap.signal(manifest.single("white"))
    noise = cap.pixel_noise()
    if white.max() <= 2 * cap.pixel_floor() + 1e-12:  # no pixel clearly above the noise
        raise AcquisitionError("the captures are all black: the white pattern's capture is "
                               "no brighter than the black one (projector off? lens cap?)",
                               cap.path(manifest.single("white")))
    bar = _bar(progress)
    corr = _correspondence(manifest, cap, white, bar)
    order = PixelOrder(manifest.grid, pixel_order)
    means = corr.reducer(order)
    if not means.seen.any():
        raise AcquisitionError("no camera pixel is lit directly by any super-pixel: is the "
                               "camera looking at the projected area?", Path(captures))
    counts = corr.counts
    if floor is None:
        floor = superpixel_noise(noise, counts) * config.ACQUIRE_FLOOR_SIGMAS
    settings = BuildSettings(
        str(Path(patterns).resolve()), str(Path(captures).resolve()), manifest.method,
        manifest.projector, manifest.superpixel, cap.shape, float(gamma),
        str(Path(black).resolve()) if black else None, float(floor), noise, corr.source)
    target = Path(output)
    # with overwrite, an existing store is replaced only by a complete one: a bad capture
    # first read while filling (Gray code reads T's captures only then) or an interrupt
    # leaves it as it was
    aside = overwrite and target.exists()
    if aside:
        check_replaceable(target, True)
    where = temporary_sibling(target) if aside else target
    try:
        writer = _open_writer(where, order, settings, tile_size, overwrite and not aside)
        _save_correspondence(writer.path, corr)
        passes = _fill(writer, manifest, cap, means, float(floor),
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
        warnings.warn(warning, stacklevel=2)
    return BuildReport(T.path, settings, order.n, int(means.seen.sum()), int(T.nnz), passes,
                       sum(cap.saturated.values()), time.perf_counter() - t0)


def superpixel_noise(pixel_noise: float, counts: np.ndarray) -> float:
    """Noise std of a camera super-pixel of mean size: a pixel's signal holds the noise of
    its capture and of the black capture (sqrt 2), averaged over the group's pixels."""
    return pixel_noise * math.sqrt(2.0 / counts[counts > 0].mean())


def _bar(progress):
    def wrap(items, desc="captures"):
        return progress_bar(items, progress=progress, desc=desc, unit="image")
    return wrap


def _correspondence(manifest, cap, white, bar) -> Correspondence:
    if manifest.graycode:
        return from_graycode(manifest, cap)
    return from_maximum_response(manifest, cap, white, cap.pixel_floor(),
                                 progress=lambda it: bar(it, "correspondence"))


def _open_writer(path: Path, order: PixelOrder, settings: BuildSettings, tile_size,
                 overwrite: bool) -> BlockCSRWriter:
    """A new store, or the interrupted build of the same settings resumed."""
    meta = {ACQUISITION_KEY: settings.to_dict()}
    shape = (order.n, order.n)
    if path.exists() and not overwrite:
        try:
            old = read_store_attrs(path)
        except StoreError:
            old = None
        if old is not None and not old.complete:
            if old.metadata.get(ACQUISITION_KEY) != json.loads(json.dumps(meta[ACQUISITION_KEY])):
                raise AcquisitionError(
                    "holds an interrupted build of other captures or settings; pass "
                    "--overwrite to start again", path)
            return BlockCSRWriter(path, shape, tile_size=old.tile_size, pixel_order=order,
                                  metadata=meta, resume=True)
    return BlockCSRWriter(path, shape, tile_size=tile_size, pixel_order=order, metadata=meta,
                          overwrite=overwrite)


def _save_correspondence(store: Path, corr: Correspondence) -> None:
    """The camera pixel -> super-pixel map, ``STORE/acquisition/correspondence.npy``
    ((Hc, Wc) int32, -1 outside every group), next to the tiles."""
    from ..atomic import atomic_output

    folder = store / ACQUISITION_KEY
    folder.mkdir(exist_ok=True)
    with atomic_output(folder / CORRESPONDENCE, "the correspondence map") as tmp:
        with open(tmp, "wb") as f:
            np.save(f, corr.labels.astype(np.int32))


def load_correspondence(store) -> np.ndarray:
    """The correspondence map saved with an acquired T, shape (Hc, Wc), int32."""
    path = Path(store) / ACQUISITION_KEY / CORRESPONDENCE
    if not path.is_file():
        raise StoreError("holds no correspondence map (not built by bigT acquire build)",
                         Path(store))
    return np.load(path, allow_pickle=False)


# --- filling the tile rows ---------------------------------------------------------

def _fill(writer: BlockCSRWriter, manifest: Manifest, cap: Captures, means: GroupMeans,
          floor: float, budget: int, progress) -> int:
    """Write every missing tile row; returns the number of passes over the captures."""
    column = _column_of(manifest, writer.pixel_order, means.seen)
    passes = 0
    missing = writer.missing_tile_rows
    while missing:
        gather = _gather_stripes if manifest.method == "stripes" else _gather_brute_force
        done = gather(writer, manifest, cap, means, floor, budget, missing, column, progress)
        missing = [i for i in missing if i not in done]
        passes += 1
    return passes


def _column_of(manifest: Manifest, order: PixelOrder, seen_matrix: np.ndarray) -> np.ndarray:
    """(n,) int64, grid index -> matrix column; -1 for unseen super-pixels (left out)."""
    col = order.inverse_permutation.copy()
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


def _gather_brute_force(writer, manifest, cap, means, floor, budget, missing, column,
                        progress) -> list[int]:
    rows = _Rows(writer, missing)
    entries = _Entries()
    for p in progress_bar(manifest.of_kind("superpixel"), progress=progress, desc="T columns",
                          unit="image"):
        col = column[p.index]
        if col < 0:
            continue  # unseen super-pixel: its column is left out
        y = means(cap.signal(p))
        r = np.flatnonzero((y >= floor) & (y > 0) & rows.mask)  # noise may be negative
        entries.add(r, np.full(len(r), col, dtype=np.int64), y[r])
        while entries.nbytes > budget and len(rows.tiles) > 1:
            rows.give_back_half()
            entries.keep_rows(rows.mask)
    rows.write(*entries.arrays(), writer.shape[1])
    return rows.tiles


def _gather_stripes(writer, manifest, cap, means, floor, budget, missing, column,
                    progress) -> list[int]:
    gh, gw = manifest.grid
    row_bytes = 8 * (gh + gw) * 2  # the stripe responses, and the entries they make
    rows = _Rows(writer, missing)
    while rows.mask.sum() * row_bytes > budget and len(rows.tiles) > 1:
        rows.give_back_half()
    index = np.flatnonzero(rows.mask)
    H = np.zeros((len(index), gh))
    V = np.zeros((len(index), gw))
    stripes = manifest.of_kind("row-stripe") + manifest.of_kind("col-stripe")
    for p in progress_bar(stripes, progress=progress, desc="stripes", unit="image"):
        y = means(cap.signal(p))[index]
        (H if p.kind == "row-stripe" else V)[:, p.band] = y
    entries = _Entries()
    for k, q in enumerate(index):
        r = np.flatnonzero((H[k] >= floor) & (H[k] > 0))
        c = np.flatnonzero((V[k] >= floor) & (V[k] > 0))
        vals = np.minimum.outer(H[k, r], V[k, c]).ravel()
        cols = column[(r[:, None] * gw + c[None, :]).ravel()]
        keep = (vals >= floor) & (cols >= 0)
        entries.add(np.full(int(keep.sum()), q, dtype=np.int64), cols[keep], vals[keep])
    rows.write(*entries.arrays(), writer.shape[1])
    return rows.tiles
