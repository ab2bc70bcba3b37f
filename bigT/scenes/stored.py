"""The out-of-core parts of a scene build: A written tile row by tile row, T's rows
multiplied against the stored A, products with stored matrices for the ground truth,
and the work directory that lets an interrupted build resume.

Memory is bounded by one budget (``memory_limit``, default
``config.SCENE_IN_MEMORY_BYTES``): a stored matrix is held whole when it fits the
budget (the common case, read once), else its tile rows are read as each product
needs them, through a tile cache of half the budget.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import stat
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from .. import config
from ..errors import DiskFullError, StoreError
from ..progress import progress_bar
from ..schedule.cache import TileCache
from ..schedule.memory import MemoryPlan
from ..schedule.operators import StoreOperand
from ..schedule.worker import product_with_stored
from ..storage import BlockCSRWriter, PixelOrder
from ..atomic import atomic_write_json
from . import radiosity
from .geometry import Patches

if TYPE_CHECKING:  # the scene module imports this one
    from .scene import Scene

#: The parameters of an interrupted build, compared with those of the next call.
BUILD_RECORD = "scene-build.json"


class StoredProduct:
    """``times_A(R, threshold)``: R @ A pruned at ``threshold``, A a stored matrix.

    A is read whole (once) when it fits half of ``memory_limit``; else the tile rows a
    product needs are read in batches (the engine's out-of-core product,
    :func:`bigT.schedule.worker.product_with_stored`) through a tile cache of the other half.

    Attributes
    ----------
    nnz : int
        A's stored entries (0: every product is empty).
    """

    def __init__(self, store, memory_limit: int):
        half = max(1, int(memory_limit) // 2)
        self.operand = StoreOperand(store, cache=TileCache(half))
        self.nnz = int(store.nnz)
        self._plan = MemoryPlan(int(memory_limit), 0, 0, half, half, half, 1)

    def __call__(self, R: sp.csr_array, threshold: float) -> sp.csr_array:
        out, _, _ = product_with_stored(R, self.operand, threshold, self._plan,
                                        self._plan.whole_bytes, config.KERNEL_THREADS)
        return out

    def release(self) -> None:
        self.operand.release()


def stored_apply(store, memory_limit: int):
    """``apply(V)``: store @ V for V of shape (n,) or (n, p), float64, one tile row at
    a time; tile rows are cached while they fit ``memory_limit`` (so a matrix that
    fits is decoded once for all the products of an eigenvalue estimate)."""
    operand = StoreOperand(store, cache=TileCache(int(memory_limit)))
    rows = [(j, *store.tile_row_range(j)) for j in np.flatnonzero(operand.nonempty)]

    def apply(V: np.ndarray) -> np.ndarray:
        V = np.asarray(V, np.float64)
        out = np.zeros((store.shape[0],) + V.shape[1:])
        for j, a, b in rows:
            out[a:b] = operand.row(j) @ V
        return out

    return apply


def work_path(path: Path) -> Path:
    """The hidden work directory of the scene built at ``path``."""
    return path.with_name(f".{path.name}.scene-build")


@contextlib.contextmanager
def disk_full_names(path: Path):
    """A disk that fills during the build becomes one DiskFullError naming the scene's
    ``path`` (not a file inside the work directory), saying that the finished tile rows
    are kept for the rerun."""
    full = (errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC))
    try:
        yield
    except (OSError, DiskFullError) as exc:
        if isinstance(exc, OSError) and exc.errno not in full:
            raise
        raise DiskFullError(f"no space left on device while building the scene; the tile "
                            f"rows finished are kept in {work_path(path).name} beside it: "
                            "free space and rerun the same command to resume", path) from None


def work_directory(path: Path, params: dict) -> tuple[Path, bool]:
    """The hidden directory ``.NAME.scene-build`` beside ``path`` where the scene is
    built, and whether it resumes an interrupted build of the same ``params``.

    A leftover of other parameters is deleted (it is bigT's own, never the user's):
    the build starts over.
    """
    work = work_path(path)
    record = work / BUILD_RECORD
    if work.exists():
        try:
            same = json.loads(record.read_text()) == params
        except (OSError, ValueError):
            same = False
        if same:
            return work, True
        shutil.rmtree(work)
    work.mkdir(parents=True)
    atomic_write_json(record, params)
    return work, False


def write_interreflection(P: Patches, albedo: np.ndarray, cut: float, path: Path,
                          pixel_order: PixelOrder, tile_size: int | None,
                          progress=None):
    """A = diag(albedo) FF written tile row by tile row at ``path`` (float64 store),
    resuming an interrupted write; memory holds one tile row's candidate pairs.

    For a colour ``pixel_order`` (``albedo`` of shape (n, 3)), the three bands'
    interreflections A_k = diag(albedo[:, k]) FF interleaved: A[3 p + k, 3 q + k] =
    A_k[p, q]; each tile row's form factors are computed once for the three bands.

    Returns
    -------
    BlockCSR, shape (n, n) (grey) or (3 n, 3 n) (colour), n = P.n
    """
    n = P.n
    c = pixel_order.channels
    writer = BlockCSRWriter(path, (c * n, c * n), tile_size=tile_size, dtype="float64",
                            pixel_order=pixel_order, resume=True)
    missing = writer.missing_tile_rows
    if missing:
        search = radiosity.face_trees(P, cut) if cut > 0 else None
        for i in progress_bar(missing, progress=progress, desc="interreflection A",
                              unit="tile row"):
            r0, r1 = writer.tile_row_range(i)
            p0, p1 = r0 // c, r1 // c  # a colour tile size is a multiple of 3
            pieces = [block for _, block in
                      radiosity.form_factor_rows(P, cut, rows=(p0, p1), search=search)]
            FF = sp.csr_array(sp.vstack(pieces, format="csr")) if pieces else \
                sp.csr_array((p1 - p0, n))
            if c == 1:
                writer.write_tile_row(i, radiosity.interreflection(FF, albedo[p0:p1]))
            else:
                writer.write_tile_row(i, radiosity.band_interreflection(FF, albedo[p0:p1]))
    return writer.finalize()


def diagonal_blocks(store, channels: int = 3) -> np.ndarray:
    """The (channels x channels) diagonal blocks of a colour store, (n_pixels, c, c)
    float64 in its matrix order (pixel p's block holds rows and columns c p .. c p + c - 1),
    read one tile row at a time."""
    c = channels
    blocks = np.zeros((store.shape[0] // c, c, c))
    for i in range(store.grid[0]):
        r0, _ = store.tile_row_range(i)
        rows = store.get_tile_row(i, columns=[i]).tocoo()  # the diagonal tile holds them
        r = rows.row.astype(np.int64) + r0
        col = rows.col.astype(np.int64)
        on = r // c == col // c
        blocks[r[on] // c, r[on] % c, col[on] % c] = rows.data[on]
    return blocks


def scratch_path(remote) -> Path:
    """Where a scene bound for object storage (``remote``, an ObjectPath) is built on
    this machine first: a directory of the system's temporary directory named after the
    URL, so a rerun of an interrupted build resumes there."""
    import hashlib
    import tempfile

    digest = hashlib.sha256(str(remote).encode()).hexdigest()[:16]
    # a directory of this user's own (0700), never one another user could have made
    mine = Path(tempfile.gettempdir()) / f"bigT-scenes-{os.getuid()}"
    mine.mkdir(mode=0o700, exist_ok=True)
    st = os.lstat(mine)
    if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o077:
        raise StoreError("is not a private directory of this user: bigT builds a scene for "
                         "object storage there; remove it", mine)
    return mine / digest / remote.name


def publish_remote(local: Path, remote, preview: Path | None, remote_preview) -> "Scene":
    """Put the scene built at ``local`` (its T store, ground truth inside) at the URL
    ``remote``, the store's root last (a reader sees it once all of it is there), and
    its preview PNG beside it; then delete the local copy and open the remote one."""
    from ..storage import upload_tree
    from .scene import load

    if remote.exists():  # check_replaceable allowed it: a bigT store, replaced
        remote.remove_tree()
    upload_tree(local, remote)
    if preview is not None and preview.is_file():
        remote_preview.write_bytes(preview.read_bytes())
    shutil.rmtree(local.parent, ignore_errors=True)
    return load(remote)
