"""The paper's 4x4 dihedral (§5.1, eq. 34) as a scene, exactly: true first bounce
F = 1.75 I."""

from __future__ import annotations

import shutil
import time

import numpy as np
import scipy.sparse as sp

from .. import config
from ..errors import BigTError, ShapeMismatchError
from ..storage import (ObjectPath, PixelOrder, as_location, check_replaceable, from_scipy,
                       temporary_sibling)
from . import radiosity
from .ground_truth import commit, write_A
from .preview import draw_preview, preview_path
from .scene import Scene, load
from .stored import publish_remote, scratch_path

#: The 4x4 transport of the paper's dihedral (eq. 34), true first bounce 1.75 I.
DIHEDRAL4_T = np.array([
    [1.7713, 0.0213, 0.1835, 0.0675],
    [0.0213, 1.7713, 0.1835, 0.0675],
    [0.1835, 0.1835, 1.7875, 0.0137],
    [0.0675, 0.0675, 0.0137, 1.7550],
])
DIHEDRAL4_F = 1.75


def dihedral4(size=None, path=None, *, overwrite=False, dtype=None, preview=True,
              **ignored) -> Scene:
    """The paper's 4x4 dihedral (§5.1, eq. 34) exactly, true first bounce F = 1.75 I.

    A = I - F T^-1 is stored as its ground truth, so that T = (I - A)^-1 F holds for
    the printed (rounded) T. ``dtype`` defaults to float64. The scene is fixed: a
    ``size`` other than (2, 2) or any other parameter (albedo, noise, ...) is refused.
    """
    if size is not None and tuple(size) != (2, 2):
        raise ShapeMismatchError(f"dihedral4 is the paper's fixed 4-patch scene (2x2), not {size}")
    if any(v not in (None, 0, 0.0, False) for v in ignored.values()):
        raise BigTError("dihedral4 is the paper's fixed scene (eq. 34); it takes no "
                        + ", ".join(sorted(k for k, v in ignored.items()
                                           if v not in (None, 0, 0.0, False))))
    t0 = time.perf_counter()
    if path is None:
        raise BigTError("path is required: the directory of the scene's T store")
    path = as_location(path)
    if isinstance(path, ObjectPath):  # built on this machine's disk, then put whole
        check_replaceable(path, overwrite)
        local = dihedral4(path=scratch_path(path), dtype=dtype, overwrite=True,
                          preview=preview)
        return publish_remote(local.path, path, preview_path(local.path) if preview else None,
                              preview_path(path))
    check_replaceable(path, overwrite)
    dtype = dtype or "float64"
    T = DIHEDRAL4_T
    F = np.full(4, DIHEDRAL4_F)
    A = np.eye(4) - np.diag(F) @ np.linalg.inv(T)
    d = np.diag(T)
    M = np.eye(4) - T / d[None, :]
    po = PixelOrder((2, 2), "row-major")
    T1 = T @ np.ones(4)
    bounces = radiosity.bounce_images(sp.csr_array(A), F, config.SCENE_SHARE_MAX_BOUNCES,
                                      config.SCENE_SHARE_TOL)
    summary = {
        "name": "dihedral4", "image_shape": [2, 2], "n": 4, "pixel_order": po.order,
        "albedo": None, "ff_cut": 0.0, "threshold": 0.0, "noise": 0.0, "noise_floor": 0.0,
        "blur": 0.0, "seed": 0, "dtype": dtype, "nnz_T": 16,
        "nnz_A": int(np.count_nonzero(A)), "bounces": 0,
        "spectral_radius": float(max(abs(np.linalg.eigvals(M)))),
        "spectral_radius_A": float(max(abs(np.linalg.eigvals(A)))),
        "spectral_radius_method": "dense", "spectral_radius_A_method": "dense",
        "bounce_shares": radiosity.light_shares(bounces),
        "exact": True, "seconds": 0.0,
        "preview": str(preview_path(path)) if preview else None,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_sibling(path)
    try:
        from_scipy(sp.csr_array(T), tmp, tile_size=2, dtype=dtype, image_shape=(2, 2))
        write_A(tmp, sp.csr_array(A), po, 2)
        commit(tmp, path, F, summary, t0)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if preview:
        draw_preview(preview_path(path), T1.reshape(2, 2), "dihedral4 (paper eq. 34)")
    return load(path)

