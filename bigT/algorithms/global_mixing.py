"""The global-mixing path of a colour inverse: T^-1 = (I (x) P^-1) U^-1 (I (x) C^-1).

With the rig's mixing global (:mod:`.mixing`), T = (I (x) C) U (I (x) P) and U is
channel-diagonal: three grey transports, interleaved (U[3p+k, 3q+k] = T_k[p, q]). The
colour inverse is then

1. the split: U = (I (x) C^-1) T (I (x) P^-1) written as a *grey* store of side 3n
   (no image shape: U's index 3p+k is the grey engine's unknown), one streaming pass;
2. U's stratified inverse by the grey engine, every option passed through: the series
   on U is the general path's series on T seen through C (M_U = I - U diag(U)^-1 and
   M_T = I - T F^-1 with F the 3x3 diagonal blocks are similar), so without pruning
   both give the same X, at a ninth of the entries in every product;
3. X = (I (x) P^-1) U^-1 (I (x) C^-1) kept factored: U^-1's tiles, hard-linked, under
   T's pixel order with the store attribute ``mixing`` {left: P^-1, right: C^-1}
   (docs/FORMAT.md, "Colour"; every product of the store applies it), published as the
   output's term like the engine's. Composed, every pixel pair with an entry in U^-1
   would be a dense 3x3 block: three times the entries, and slower than the general
   path.

The output is an inverse store like any other (docs/FORMAT.md, "The inverse store"):
its record holds the grey series' record, T's fingerprint, ``colour_path: "global"``
and the mixing. The work (U and its grey inverse) lives in the hidden directory
``.global-mixing`` inside the output: a fixed name (not a writer's hidden sibling,
whose PID would change) so that a rerun after an interruption finds it and the grey
inverse resumes; it is deleted once X is published (X's tiles are links to its
files, so they stay).
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import scipy.sparse as sp

from ..storage import (InverseStore, ObjectPath, StoreAttrs, create_store, finalize_store,
                       temporary_sibling, write_tile_row)
from ..storage import open as open_store
from ..storage.channel_mixing import ChannelMixing
from ..storage.inverse_store import jsonable
from ..storage.locks import READER_LEASE, WRITER_LOCK
from ..storage.replace import remove_tree, write_root_attrs
from ..storage.writer import BlockCSRWriter
from .first_bounce import FirstBounce
from .fingerprint import inverse_fingerprint
from .mixing import ColourMixing, ColourPathChoice, pixel_blocks, row_chunks, unmix
from .records import SeriesRecord
from .report import InverseReport
from .settings import Thresholds

#: The work directory inside the output (U and its grey inverse).
WORK_DIR = ".global-mixing"


@dataclass(frozen=True)
class ColourInverseReport(InverseReport):
    """An :class:`InverseReport` of a colour inverse, with the path it took and why.

    On the global path the per-term table is U's grey series (its nnz(X) counts U^-1's
    entries); ``nnz_X`` is the colour X's (U^-1's: X is stored factored),
    ``seconds_split`` the streaming pass before the grey inverse and ``seconds_publish``
    the publishing of X after it (linking U^-1's tiles), and ``mixing_residual`` the
    cross-channel residue the verification measured.
    """

    colour_path: str = "general"
    colour_reason: str = ""
    mixing_residual: float | None = None
    nnz_X: int | None = None
    seconds_split: float = 0.0
    seconds_publish: float = 0.0


def with_colour_path(report: InverseReport, choice: ColourPathChoice,
                     **more) -> ColourInverseReport:
    """``report`` with the colour path ``choice`` (and the ``more`` fields) added."""
    fields = {f.name: getattr(report, f.name) for f in dataclasses.fields(InverseReport)}
    residual = None if choice.mixing is None else choice.mixing.residual
    return ColourInverseReport(**{**fields, **more}, colour_path=choice.path,
                               colour_reason=choice.reason, mixing_residual=residual)


def global_mixing_inverse(T, out, choice: ColourPathChoice, options: Mapping[str, Any],
                          grey_inverse: Callable[..., InverseReport],
                          t_start: float | None = None) -> ColourInverseReport:
    """The inverse of the colour store ``T`` into the inverse store ``out`` by three
    grey inverses between the un-mixings of ``choice.mixing``.

    Parameters
    ----------
    T : BlockCSR, colour (channels 3), shape (3n, 3n)
    out : str or Path
    choice : ColourPathChoice
        ``path == "global"``, its mixing verified.
    options : mapping
        :func:`stratified_inverse`'s keyword arguments for the grey run (``terms``,
        ``prune``, ``method``, ``first_bounce``, ...), passed through.
    grey_inverse : callable
        The grey entry, ``grey_inverse(U, out, **options)``.
    t_start : float, optional
        ``time.perf_counter()`` when the call began (the mixing's detection and
        verification then count in the report's ``seconds``); default now.
    """
    t_start = time.perf_counter() if t_start is None else t_start
    mixing = choice.mixing
    thresholds = Thresholds(options["prune"], options.get("prune_feed"),
                            options.get("prune_operator"))
    store = InverseStore(out)
    params = global_fingerprint(T, mixing, thresholds, options["method"],
                                options["first_bounce"])
    try:
        held = SeriesRecord.from_stored(
            store.open_or_create(params, options.get("overwrite", False)), store.path)
        if held.term is not None and held.term >= options["terms"]:
            return _already_held(T, store, held, choice, options, t_start)
        work = store.path / WORK_DIR
        t0 = time.perf_counter()
        U = split(T, mixing, work / "U")
        t_split = time.perf_counter() - t0
        grey = grey_inverse(U, work / "U_inverse", **{**options, "overwrite": False})
        t0 = time.perf_counter()
        grey_record = SeriesRecord.from_stored(InverseStore(grey.path).read_record(),
                                               grey.path)
        X = factored_inverse(open_store(grey.path), T, mixing, store, grey_record.dir)
        publish(store, T, X, grey_record, params, mixing)
        t_publish = time.perf_counter() - t0
        store.clean(keep={grey_record.dir})
        remove_tree(work)
    finally:
        store.close()
    return with_colour_path(grey, choice, path=str(store.path), nnz_T=int(T.nnz),
                            nnz_X=int(X.nnz), seconds=time.perf_counter() - t_start,
                            seconds_split=t_split, seconds_publish=t_publish)


def global_fingerprint(T, mixing: ColourMixing, thresholds: Thresholds, method: str,
                       first_bounce: str) -> dict:
    """What the global-path inverse depends on: T's fingerprint (as the engine's), the
    series' settings, F's kind, the path and the mixing (a rerun with another mixing is
    refused)."""
    kind = FirstBounce(first_bounce, np.empty(0), np.empty(0), np.empty(0, bool), 0, "")
    params = inverse_fingerprint(T, kind, thresholds, method)
    params["first_bounce"] = {"kind": first_bounce}  # of U's, which is not stored apart
    return {**params, "colour_path": "global", "mixing": mixing.to_json()}


# --- 1. the split ------------------------------------------------------------------

def split(T, mixing: ColourMixing, path: Path):
    """U = (I (x) C^-1) T (I (x) P^-1) without its cross-channel entries (below the
    verified residue), as a grey store at ``path`` of T's tile size and dtype (tile
    rows already complete there are kept: a resumed split). Returns it, opened."""
    if (path / "zarr.json").is_file():
        try:
            return open_store(path)  # complete: an earlier run's
        except Exception:  # noqa: BLE001 -- incomplete: resumed below
            pass
    writer = BlockCSRWriter(path, T.shape, tile_size=T.tile_size, dtype=T.dtype,
                            metadata={"mixing_of": str(T.path)}, resume=True)
    done = set(writer.completed_tile_rows)
    parts: dict[int, list] = {}
    for start, rows in row_chunks(T):
        i = start // T.tile_size
        if i in done:
            continue
        parts.setdefault(i, []).append(_unmixed_rows(rows, mixing))
        a, b = T.tile_row_range(i)
        if start + rows.shape[0] == b:  # the tile row's last chunk
            writer.write_tile_row(i, sp.vstack(parts.pop(i), format="csr"))
    return writer.finalize()


def _unmixed_rows(rows: sp.csr_array, mixing: ColourMixing) -> sp.csr_array:
    """The in-channel entries of C^-1 B P^-1 for every pixel block B of ``rows``."""
    p, q, blocks = pixel_blocks(rows)
    u = np.einsum("bkk->bk", unmix(blocks, mixing))
    k = np.arange(3)
    r = (3 * p[:, None] + k).ravel()
    c = (3 * q[:, None] + k).ravel()
    return sp.csr_array((u.ravel(), (r, c)), shape=rows.shape)


# --- 3. X, factored ----------------------------------------------------------------

def factored_inverse(Xu, T, mixing: ColourMixing, store: InverseStore, k: int):
    """X = (I (x) P^-1) U^-1 (I (x) C^-1) kept factored as term ``k``'s store ``X`` of
    ``store``: U^-1's tiles (hard links, a copy where the file system cannot link) under
    T's (colour) pixel order with the ``mixing`` attribute {left: P^-1, right: C^-1}
    (docs/FORMAT.md, "Colour"), so X holds U^-1's entries, not a dense 3x3 block per
    pixel pair. A store an interrupted run left there is rebuilt (links are cheap).
    Where the grey engine cut U in tiles that are not whole pixels (it may halve T's
    tile size), U^-1's rows are rewritten in T's tiles instead (a copy, still factored).
    Returns X, opened."""
    attrs = Xu.attrs.replace(
        pixel_order=T.pixel_order,
        mixing=ChannelMixing(mixing.projector_inverse, mixing.camera_inverse),
        metadata={"inverse": {"term": k, "complete": False, "colour_path": "global"}})
    path = store.term_path(k, "X")
    if isinstance(path, ObjectPath):  # no rename, no link: copied in the server, in place
        if path.exists():
            path.remove_tree()
        if Xu.tile_size % 3 == 0:
            Xu.path.copy_tree_to(path)
            write_root_attrs(path, attrs)
        else:
            _retiled(Xu, attrs.replace(tile_size=T.tile_size, complete=False, nnz=None), path)
        return finalize_store(path)
    aside = temporary_sibling(path)
    if Xu.tile_size % 3 == 0:
        shutil.copytree(Xu.path, aside, copy_function=_link_or_copy,
                        ignore=shutil.ignore_patterns(READER_LEASE, WRITER_LOCK))
        write_root_attrs(aside, attrs)
    else:
        _retiled(Xu, attrs.replace(tile_size=T.tile_size, complete=False, nnz=None), aside)
    if path.exists():
        shutil.rmtree(path)
    os.rename(aside, path)
    return finalize_store(path)  # the linked copy is complete already: opened


def _retiled(Xu, attrs: StoreAttrs, path: Path) -> None:
    """Xu's rows written at ``path`` as a store of ``attrs`` (its tile size), every tile
    row complete (finalized once it is moved into place)."""
    create_store(path, attrs)
    for i in range(attrs.grid[0]):
        write_tile_row(path, attrs, i, Xu.get_rows(*attrs.tile_row_range(i)))


def _link_or_copy(src: str, dst: str) -> None:
    """``dst`` a hard link of ``src`` (tiles are never edited in place), else a copy."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


# --- publishing --------------------------------------------------------------------

def publish(store: InverseStore, T, X, grey: SeriesRecord, params: dict,
            mixing: ColourMixing) -> None:
    """Publish X as the output's term: the grey series' record (history, spectral
    radius, residual: U's) under the colour T's fingerprint, with the path and the
    mixing, in the engine's order (X's own record, the redirect, the root record)."""
    colour = {"colour_path": "global", "mixing": mixing_record(mixing)}
    record = grey.replace(params=params, tile_size=T.tile_size).to_stored()
    record = record.replace(details={**record.details, **colour})
    Xu_meta = dict(open_store(store.path / WORK_DIR / "U_inverse").metadata["inverse"])
    store.publish(record, X, jsonable({**Xu_meta, **colour}))


def mixing_record(mixing: ColourMixing) -> dict:
    """The ``mixing`` object of the inverse's records: C, P, where they came from and
    the cross-channel residue measured."""
    return {**mixing.to_json(), "source": mixing.source, "residual": mixing.residual}


def _already_held(T, store: InverseStore, held: SeriesRecord, choice: ColourPathChoice,
                  options: Mapping[str, Any], t_start: float) -> ColourInverseReport:
    """The report of a run that found its term held (nothing computed)."""
    th = Thresholds(options["prune"], options.get("prune_feed"), options.get("prune_operator"))
    X = open_store(store.path)
    report = InverseReport(
        path=str(store.path), terms=held.term, requested_terms=options["terms"],
        method=options["method"], prune=th.prune, prune_feed=th.feed,
        prune_operator=th.operator, first_bounce=options["first_bounce"],
        spectral_radius=held.spectral_radius, spectral_uncertainty=held.spectral_uncertainty,
        spectral_method=held.spectral_method, spectral_computed=False,
        excluded_pixels=held.excluded_pixels or 0, residual=held.residual,
        stopped=f"already held term {held.term}", resumed_from=held.term, products=0,
        seconds=time.perf_counter() - t_start, n=T.shape[0], nnz_T=int(T.nnz),
        history=held.history, tile_size=held.tile_size or T.tile_size)
    return with_colour_path(report, choice, nnz_X=int(X.nnz))
