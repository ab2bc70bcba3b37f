"""The scene's ground truth on disk: the group ``ground_truth/`` inside the T store
(docs/FORMAT.md), holding A (a bigT store), F ((n,) float64) and the summary, and the
commit that moves a complete scene into place.

Layout::

    T.zarr/                    bigT store of T; metadata["scene"] = the summary
      ground_truth/            zarr group, attributes["bigT_scene"] = summary
        A/                     bigT store of A (matrix order of T)
        F/                     float64 (n,) first bounce, matrix order
                               (colour: (n_pixels, 3, 3), its diagonal blocks)
        camera/, projector/    colour only: float64 (n_pixels, 3, 3), the rig's C_p, P_q

A colour scene whose mixing is global also records it in T's metadata:
``metadata["mixing"] = {"camera": C, "projector": P}`` (3x3 lists).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import zarr

from .. import config
from ..storage import from_scipy, move_into_place, write_group
from ..storage import open as open_store

GROUND_TRUTH = "ground_truth"
SCENE_ATTR = "bigT_scene"


def new_ground_truth_group(root: Path) -> Path:
    """The empty ground-truth group of the T store at ``root`` (created when missing)."""
    gt = root / GROUND_TRUTH
    if not gt.exists():
        gt.mkdir()
        write_group(gt, {})
    return gt


def write_A(root: Path, A: sp.csr_array, po, tile_size) -> None:
    """The ground-truth group of the scene at ``root`` with A in it (a small scene's A
    made in memory; built scenes write theirs tile row by tile row)."""
    gt = root / GROUND_TRUTH
    gt.mkdir()
    write_group(gt, {})
    from_scipy(A, gt / "A", tile_size=tile_size, dtype="float64", image_shape=po.image_shape,
               pixel_order=po.order, image_tile=po.image_tile, input_order="matrix")


def write_F(gt: Path, F: np.ndarray, name: str = "F") -> None:
    """F (first bounce, (n,) float64, or (n_pixels, 3, 3) blocks for colour) into the
    ground-truth group ``gt`` (as array ``name``: the rig's blocks are written alike)."""
    F = np.asarray(F, np.float64)
    per_row = int(np.prod(F.shape[1:], dtype=np.int64))
    rows = max(1, min(len(F), config.CHUNK_ELEMENTS // max(1, per_row)))
    arr = zarr.create_array(store=str(gt / name), shape=F.shape, dtype="float64",
                            chunks=(rows, *F.shape[1:]), fill_value=float("nan"),
                            overwrite=True)
    arr[...] = F


def commit(tmp: Path, path: Path, F, summary: dict, t_start: float, *,
           rig_blocks: dict | None = None, mixing: dict | None = None) -> None:
    """Add F to the ground truth of the complete T store built at ``tmp`` (its A is
    there already), record the summary (in the ground-truth group and in T's metadata,
    so ``bigT info`` shows it) and move the scene into place at ``path``.

    Colour: ``rig_blocks`` ({"camera": C_p, "projector": P_q}, each (n_pixels, 3, 3))
    are written beside F, and a global ``mixing`` ({"camera": C, "projector": P}) into
    T's metadata, where the inverse engine reads it."""
    write_F(tmp / GROUND_TRUTH, F)
    for name, blocks in (rig_blocks or {}).items():
        write_F(tmp / GROUND_TRUTH, blocks, name)
    summary["seconds"] = time.perf_counter() - t_start
    write_group(tmp / GROUND_TRUTH, {SCENE_ATTR: summary})
    open_store(tmp).update_metadata(scene=summary, **({} if mixing is None else
                                                      {"mixing": mixing}))
    move_into_place(tmp, path)
