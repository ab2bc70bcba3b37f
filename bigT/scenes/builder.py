"""Synthetic projector-camera scenes written as bigT stores with their ground truth.

A scene is built in four steps, each in bounded memory:

1. geometry (:mod:`.geometry`): the surface patch seen by every pixel, renumbered into
   the store's pixel order (image-tile-major by default, docs/DESIGN.md "Pixel order");
2. interreflection (:mod:`.radiosity`, :mod:`.stored`): A = diag(albedo) FF, written
   tile row by tile row into the ground truth's store;
3. transport: T = (sum_k A^k) F [G] (paper eq. 6/8) one tile row at a time with the
   pruned products of the kernels layer against the stored A (held whole only within
   ``memory_limit``), each tile row written by :class:`bigT.BlockCSRWriter` as soon as
   it is done, so T never sits in memory whole; the ground truth (spectral radii,
   bounce shares) is then computed from the stores;
4. acquisition (optional): Gaussian defocus G of the projector, additive camera noise
   on every stored entry and a noise floor below which entries are dropped.

Layout on disk: ``path`` is the T store (a bigT block-CSR group) and holds the ground
truth in its subgroup ``ground_truth/``::

    T.zarr/                    bigT store of T; metadata["scene"] = the summary below
      ground_truth/            zarr group, attributes["bigT_scene"] = summary
        A/                     bigT store of A (matrix order of T)
        F/                     float64 (n,) first bounce, matrix order

For a noise-free scene without truncation (``threshold=0``) and without blur, the
exact inverse is F^-1 (I - A); :func:`exact_inverse_rows` gives it tile row by tile
row, so the error of an inverse can be measured at full scale without any dense
inversion (or on a sample of rows: :meth:`Scene.inverse_error`). The whole scene is
written in the hidden work directory ``.NAME.scene-build`` beside ``path`` and moved
into place when complete: a failed or interrupted call leaves ``path`` as it was, and
the next call with the same parameters resumes from the tile rows done.
"""

from __future__ import annotations

import hashlib
import math
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from .. import config
from ..errors import BigTError, InvalidMatrixError, ShapeMismatchError, StoreError
from ..storage import BlockCSRWriter, PixelOrder, from_scipy
from ..storage import open as open_store
from ..progress import progress_bar
from ..storage import check_replaceable, move_into_place, temporary_sibling, write_group
from ..spectral import SpectralRadius, spectral_radius
from .catalog import DEFAULT_SIZES, DENSITIES, SCENE_NAMES  # noqa: F401 (re-exported)
from . import geometry, radiosity, stored

#: The 4x4 transport of the paper's dihedral (eq. 34), true first bounce 1.75 I.
DIHEDRAL4_T = np.array([
    [1.7713, 0.0213, 0.1835, 0.0675],
    [0.0213, 1.7713, 0.1835, 0.0675],
    [0.1835, 0.1835, 1.7875, 0.0137],
    [0.0675, 0.0675, 0.0137, 1.7550],
])
DIHEDRAL4_F = 1.75

GROUND_TRUTH = "ground_truth"
SCENE_ATTR = "bigT_scene"


@dataclass
class Scene:
    """A scene on disk and its ground truth.

    Attributes
    ----------
    path : pathlib.Path
        The T store; the ground truth is in ``path / "ground_truth"``.
    T, A : BlockCSR, shape (n, n)
        Light transport and interreflection (matrix order, ``pixel_order``).
    F : ndarray, (n,) float64
        True first bounce (diagonal of F), matrix order.
    pixel_order : PixelOrder
    summary : dict
        Name, parameters, nnz, spectral radii, bounce shares, timings (JSON).
    """

    path: Path
    T: object
    A: object
    F: np.ndarray
    pixel_order: PixelOrder
    summary: dict = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.summary.get("name", "")

    @property
    def spectral_radius(self) -> float:
        """Spectral radius of M = I - T F^-1 with F = diag(T), the first bounce
        ``bigT invert`` uses by default: all eigenvalues for up to
        ``config.SPECTRAL_RADIUS_DENSE_MAX`` pixels, else ARPACK to a relative
        ``config.SCENE_SPECTRAL_RTOL`` (the Ritz residual is in
        ``summary["spectral_radius_uncertainty"]``)."""
        return self.summary.get("spectral_radius")

    @property
    def bounce_shares(self) -> list[float]:
        """Each bounce's share of the light of a white projector image: sum(A^k F G 1) /
        sum_j sum(A^j F G 1) for k = 0, 1, ... (G = I without blur), adding up to 1; the
        bounces are listed until one carries less than ``config.SCENE_SHARE_TOL`` of
        the first."""
        return self.summary.get("bounce_shares", [])

    @property
    def exact(self) -> bool:
        """True when F^-1 (I - A) is the exact inverse of T (no truncation, noise, blur)."""
        return bool(self.summary.get("exact"))

    @property
    def preview(self) -> Path | None:
        p = self.summary.get("preview")
        return None if p is None else Path(p)

    def exact_inverse_rows(self, i: int) -> sp.csr_array:
        """Tile row ``i`` of F^-1 (I - A), shape (rows_i, n), float64."""
        return exact_inverse_rows(self.A, self.F, i)

    def inverse_error(self, X, sample: int | None = None, seed: int = 0) -> float:
        """||X - F^-1 (I - A)||_F / ||F^-1 (I - A)||_F, tile row by tile row, over
        all rows or a random sample of them.

        Parameters
        ----------
        X : BlockCSR of T's shape and pixel order (any tile size), or (n,) ndarray
            An inverse on disk, or the diagonal of a diagonal one (e.g. 1 / diag(T)).
        sample : int, optional
            Measure on this many rows drawn uniformly without replacement (seeded by
            ``seed``) instead of all n: the error of a full-HD inverse in one read of
            the tile rows, with no row of the exact inverse formed beyond the sample.

        Returns
        -------
        float
            The relative error against the exact inverse of the scene, without any dense
            matrix. F^-1 (I - A) inverts the noise-free, untruncated scene without blur
            (:attr:`exact`); otherwise this is the distance to that scene's inverse.
        """
        T = self.T
        n = T.shape[0]
        rows = _inverse_rows(X, T)
        chosen = None
        if sample is not None and sample < n:
            chosen = np.sort(np.random.default_rng(seed).choice(n, int(sample), replace=False))
        num = den = 0.0
        for i in range(T.grid[0]):
            r0, r1 = T.tile_row_range(i)
            keep = None if chosen is None else chosen[(chosen >= r0) & (chosen < r1)] - r0
            if keep is not None and not len(keep):
                continue
            ref, got = self.exact_inverse_rows(i), rows(i)
            if keep is not None:
                ref, got = ref[keep], got[keep]
            diff = sp.csr_array(got - ref)
            num += float(np.sum(diff.data ** 2))
            den += float(np.sum(ref.data ** 2))
        return math.sqrt(num / den) if den else 0.0

    def describe(self) -> str:
        s = self.summary
        H, W = s["image_shape"]
        lines = [
            f"scene {s['name']} {H}x{W} (n = {s['n']}), albedo {s['albedo']}, "
            f"form-factor cut {s['ff_cut']:g}, threshold {s['threshold']:g}, "
            f"noise {s['noise']:g}, blur {s['blur']:g}",
            f"  T: {s['nnz_T']} nonzeros ({s['nnz_T'] / s['n']:.1f} per row), "
            f"A: {s['nnz_A']} ({s['nnz_A'] / s['n']:.1f} per row), up to {s['bounces']} "
            f"bounces per row",
            f"  spectral radius of M = I - T diag(T)^-1: {_radius(s['spectral_radius'])}"
            f"{_uncertainty(s.get('spectral_radius_uncertainty'))}; "
            f"of A: {_radius(s['spectral_radius_A'])}"
            f"{_uncertainty(s.get('spectral_radius_A_uncertainty'))}",
            "  bounce shares of the light of a white image (adding up to 100%): "
            + ", ".join(f"{100 * v:.3g}%" for v in s["bounce_shares"]),
            f"  built in {s['seconds']:.1f} s"
            + (f"; preview {s['preview']}" if s.get("preview") else ""),
            "  exact inverse F^-1 (I - A) " + ("holds" if s["exact"] else
                                               "holds up to truncation/noise/blur"),
        ]
        return "\n".join(lines)


def _inverse_rows(X, T):
    """``rows(i)``: tile row ``i`` of T's grid of the inverse ``X`` (a store, or the
    (n,) diagonal of a diagonal inverse), float64 CSR."""
    if isinstance(X, np.ndarray):
        if X.shape != (T.shape[0],):
            raise ShapeMismatchError(f"a diagonal X needs {T.shape[0]} entries, got {X.shape}")
        diag = np.asarray(X, np.float64)

        def rows(i):
            r0, r1 = T.tile_row_range(i)
            return sp.csr_array((diag[r0:r1], np.arange(r0, r1), np.arange(r1 - r0 + 1)),
                                shape=(r1 - r0, T.shape[1]))
        return rows
    where = getattr(X, "path", None)
    if X.shape != T.shape:
        raise ShapeMismatchError(f"X is {X.shape}, the scene is {T.shape}", where)
    if X.pixel_order is not None and X.pixel_order != T.pixel_order:
        raise ShapeMismatchError(f"X's pixel order {X.pixel_order} is not the scene's "
                                 f"{T.pixel_order}", where)

    def rows(i):
        return sp.csr_array(X.get_rows(*T.tile_row_range(i)), dtype=np.float64)
    return rows


def exact_inverse_rows(A, F, i: int) -> sp.csr_array:
    """Tile row ``i`` of F^-1 (I - A), shape (rows_i, n), float64.

    A : BlockCSR (n, n), the scene's interreflection; F : (n,) first bounce, both in
    matrix order."""
    n = A.shape[0]
    r0, r1 = A.tile_row_range(i)
    Arows = sp.csr_array(A.get_tile_row(i), dtype=np.float64)
    eye = sp.csr_array((np.ones(r1 - r0), np.arange(r0, r1), np.arange(r1 - r0 + 1)),
                       shape=(r1 - r0, n))
    return sp.csr_array(sp.diags_array(1.0 / np.asarray(F[r0:r1], np.float64)) @ (eye - Arows))


# --- building ----------------------------------------------------------------------------

def _resolve_density(density, ff_cut, threshold, n):
    """(density label, form-factor cut, threshold) from a preset name or a cut, with
    explicit overrides. No preset: "exact" up to ``config.SCENE_EXACT_MAX_N`` pixels,
    else "sparse"."""
    if density is None:
        density = "exact" if n <= config.SCENE_EXACT_MAX_N else "sparse"
    if isinstance(density, str):
        if density not in DENSITIES:
            raise BigTError(f"density must be one of {tuple(DENSITIES)} or a number, "
                            f"got {density!r}")
        cut, thr = DENSITIES[density]
    else:
        density = float(density)
        cut, thr = density, DENSITIES["sparse"][1]
    if ff_cut is not None or threshold is not None:
        density = "custom"
    cut = cut if ff_cut is None else float(ff_cut)
    thr = thr if threshold is None else float(threshold)
    _check_nonnegative(ff_cut=cut, threshold=thr)
    return density, cut, thr


def _check_nonnegative(**values):
    for name, v in values.items():
        if not (math.isfinite(float(v)) and float(v) >= 0):
            raise BigTError(f"{name} must be a finite number >= 0, got {v}")


def _albedo_vector(albedo, size, perm) -> tuple[np.ndarray, object]:
    H, W = size
    a = np.asarray(albedo, dtype=np.float64)
    if a.ndim == 0:
        vec = np.full(H * W, float(a))
        label = float(a)
    elif a.shape == (H, W):
        vec = a.ravel()[perm]
        label = "texture"
    else:
        raise ShapeMismatchError(f"albedo must be a number or an (H, W) = {size} texture, "
                                 f"got shape {a.shape}")
    if not np.isfinite(vec).all() or (vec <= 0).any() or (vec >= 1).any():
        raise InvalidMatrixError("albedo must lie in (0, 1): a black surface (0) sends no "
                                 "light back and makes T singular, one reflecting all light "
                                 "(1) makes the bounce series diverge")
    return vec, label


def _patches(name, size):
    if name == "corner":
        return geometry.wall_corner(size, concave=True)
    if name == "convex":
        return geometry.wall_corner(size, concave=False)
    if name == "flat":
        return geometry.flat_wall(size)
    if name == "cornell":
        return geometry.cornell_box(size)
    if name == "hemispheres":
        return geometry.hemisphere_field(size)
    raise BigTError(f"unknown scene {name!r}; choose from {SCENE_NAMES}")


def _add_noise(rows: sp.csr_array, noise: float, floor: float, rng) -> sp.csr_array:
    """Camera noise on every stored entry, then the noise floor: entries below ``floor``
    and those the noise made zero or negative are dropped, as in a thresholded capture
    (T stays nonnegative, which the spectral radius estimate relies on)."""
    rows = rows.copy()
    if noise > 0:
        rows.data = rows.data + rng.normal(0.0, noise, rows.data.shape)
    rows.data[rows.data < max(floor, np.finfo(np.float64).tiny)] = 0.0
    rows.eliminate_zeros()
    return rows


def _finite(value: float) -> float | None:
    """JSON has no inf or NaN: an undetermined radius is stored as null."""
    return float(value) if math.isfinite(value) else None


def _radius(value) -> str:
    return "undetermined" if value is None else f"{value:.4f}"


def _uncertainty(value) -> str:
    """`` +- 1.2e-09`` (Ritz residual of the ground truth), or nothing for older scenes."""
    return "" if value is None else f" +- {value:.1e}"


def _spectral_radius_T(times_T, d) -> SpectralRadius:
    """rho(M) for M = I - T diag(d)^-1 on the pixels with d > 0, to
    ``config.SCENE_SPECTRAL_RTOL``; ``times_T(V)`` is T @ V."""
    inv = np.zeros_like(d)
    inv[d > 0] = 1.0 / d[d > 0]
    lit = d > 0

    def minus_M(V):
        # (T - diag(d)) diag(d)^-1 V: the diagonal cancels exactly (V - T diag(d)^-1 V
        # left 1e-16 of rounding on a diagonal T)
        W = V * inv[:, None]
        return times_T(W) - d[:, None] * W

    return spectral_radius(minus_M, len(d), lit, rtol=config.SCENE_SPECTRAL_RTOL,
                           max_products=config.SCENE_SPECTRAL_MAX_PRODUCTS)


def _write_A(root: Path, A: sp.csr_array, po, tile_size):
    """The ground-truth group of the scene at ``root`` with A in it (a small scene's A
    made in memory; built scenes write theirs tile row by tile row)."""
    gt = root / GROUND_TRUTH
    gt.mkdir()
    write_group(gt, {})
    from_scipy(A, gt / "A", tile_size=tile_size, dtype="float64", image_shape=po.image_shape,
               pixel_order=po.order, image_tile=po.image_tile, input_order="matrix")


def _write_F(gt: Path, F: np.ndarray) -> None:
    """F (first bounce, (n,) float64) into the ground-truth group ``gt``."""
    import zarr

    arr = zarr.create_array(store=str(gt / "F"), shape=F.shape, dtype="float64",
                            chunks=(max(1, min(len(F), config.CHUNK_ELEMENTS)),),
                            fill_value=float("nan"), overwrite=True)
    arr[:] = F


def _preview(path: Path, image: np.ndarray, title: str) -> Path:
    """T 1 (the camera's view of a white projector image) with three horizontal scan
    lines drawn on it and plotted beside it (paper Fig. 8)."""
    from ..figures import pyplot, save_figure

    plt = pyplot()
    H, W = image.shape
    rows = distinct_rows(image, 3)
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 3.8), gridspec_kw={"width_ratios": [1, 1.4]})
    ax0.imshow(image, cmap="gray", vmin=0, interpolation="nearest")
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for k, r in enumerate(rows):
        ax0.axhline(r, color=colours[k], lw=1)
        ax1.plot(image[r], color=colours[k], lw=1.3, label=f"row {r}")
    ax0.set_title("T 1 (white projector image)", fontsize=9)
    ax0.set_xticks([])
    ax0.set_yticks([])
    ax1.set_xlabel("column")
    ax1.set_ylabel("intensity")
    ax1.set_title("horizontal scan lines", fontsize=9)
    ax1.grid(alpha=0.3)
    ax1.legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path, dpi=100)


def distinct_rows(image: np.ndarray, k: int) -> list[int]:
    """``k`` rows of ``image`` whose profiles differ most, ascending: the centre row,
    then greedily the row farthest (L2) from those chosen. A scene symmetric top to
    bottom (the corner) would draw two of the quarter rows on top of each other."""
    image = np.asarray(image, np.float64)
    H = image.shape[0]
    chosen = [H // 2]
    dist = np.linalg.norm(image - image[chosen[0]], axis=1)
    edge = H // 8  # a line drawn on the frame of the picture would not be seen
    dist[:edge] = dist[H - edge:] = -1.0
    while len(chosen) < min(k, H):
        r = int(np.argmax(dist))
        if dist[r] <= 0:  # every row left repeats one chosen: nothing more to show
            break
        chosen.append(r)
        dist = np.minimum(dist, np.linalg.norm(image - image[r], axis=1))
    return sorted(chosen)


def preview_path(path: Path) -> Path:
    """Where the preview PNG of the scene stored at ``path`` goes: beside the store."""
    name = path.name[:-5] if path.name.endswith(".zarr") else path.name
    return path.with_name(f"{name}-preview.png")


def build(name: str, size=None, path=None, *, albedo=0.6, density=None, ff_cut=None,
          threshold=None, noise=0.0, noise_floor=None, blur=0.0, seed=0, tile_size=None,
          pixel_order="tile-major", dtype="float32", overwrite=False, preview=True,
          progress=None, memory_limit=None) -> Scene:
    """Build a named scene at ``path`` (see :func:`corner` and friends).

    Parameters
    ----------
    name : {"corner", "convex", "flat", "cornell", "hemispheres"}
    size : (H, W), optional
        Image size; default ``DEFAULT_SIZES[name]``. n = H W.
    path : str or os.PathLike
        Directory of the T store (e.g. ``corner.zarr``); the preview PNG goes beside it.
    albedo : float in (0, 1) or (H, W) ndarray
        Lambertian albedo, one value or a texture (row-major image).
    density : {"exact", "sparse", "dense"} or float, optional
        Preset of (form-factor cut, threshold); a float is a form-factor cut (with the
        sparse threshold). Default: "exact" up to ``config.SCENE_EXACT_MAX_N`` pixels
        (T is then dense: every bounce of every pair), else "sparse".
    ff_cut : float, optional
        Overrides the preset's form-factor cut: pairs with max(FF_ij, FF_ji) below it
        exchange no light (controls the nonzeros of A).
    threshold : float, optional
        Overrides the preset's truncation of T: the bounce series of a row stops when
        the newest bounce's largest entry is below it, bounces are pruned at
        ``config.SCENE_PRUNE_FRACTION`` of it, and entries of T below it are dropped.
        0: no truncation (exact).
    noise : float
        Standard deviation of additive camera noise on every stored entry of T.
    noise_floor : float, optional
        Entries of T below it are dropped after the noise; default 3 * noise.
    blur : float
        Standard deviation (pixels) of the projector's Gaussian defocus (0: none).
    seed : int
        Seeds the noise (tile row i uses the stream (seed, i)).
    tile_size : int, optional
        Default ``config.DEFAULT_TILE_SIZE``.
    pixel_order : {"tile-major", "row-major"}
    dtype : {"float32", "float64"}
        dtype of T's values (A, F and the ground truth are float64).
    overwrite : bool
        Replace an existing bigT store at ``path``.
    preview : bool
        Write ``<name>-preview.png`` beside the store.
    progress : bool, optional
        Progress bars (None: on a terminal only).
    memory_limit : int, optional
        Bytes the build may hold of A and T at once (default
        ``config.SCENE_IN_MEMORY_BYTES``): a matrix within it is read whole once, a
        larger one tile row by tile row. The build is resumable: an interrupted call
        leaves its work in ``.NAME.scene-build`` beside ``path``, and the next call
        with the same parameters goes on from the tile rows done.

    Returns
    -------
    Scene
    """
    t_start = time.perf_counter()
    if name not in DEFAULT_SIZES:
        raise BigTError(f"unknown scene {name!r}; choose from {tuple(DEFAULT_SIZES)} "
                        "(dihedral4 through bigT.scenes.dihedral4 or make)")
    if path is None:
        raise BigTError("path is required: the directory of the scene's T store")
    path = Path(os.fspath(path))
    size = tuple(int(s) for s in (DEFAULT_SIZES[name] if size is None else size))
    if len(size) != 2 or min(size) < 1:
        raise ShapeMismatchError(f"size must be (H, W) with H, W >= 1, got {size}")
    floor = 3.0 * float(noise) if noise_floor is None else float(noise_floor)
    _check_nonnegative(noise=noise, noise_floor=floor, blur=blur)
    noise, blur = float(noise), float(blur)
    check_replaceable(path, overwrite)
    H, W = size
    n = H * W
    po = PixelOrder(size, pixel_order)
    perm = po.permutation
    density, cut, thr = _resolve_density(density, ff_cut, threshold, n)
    albedo_vec, albedo_label = _albedo_vector(albedo, size, perm)
    radiosity.check_all_pairs(n, cut)

    P = _patches(name, size).take(perm)
    f = albedo_vec * P.first_bounce_gain()
    G = radiosity.gaussian_blur_matrix(size, blur, perm) if blur > 0 else None
    memory_limit = int(memory_limit or config.SCENE_IN_MEMORY_BYTES)
    exact = thr == 0 and noise == 0 and floor == 0 and blur == 0
    params = {
        "name": name, "image_shape": [H, W], "n": n, "pixel_order": po.order,
        "albedo": albedo_label, "density": density, "ff_cut": cut, "threshold": thr,
        "noise": noise, "noise_floor": floor, "blur": blur, "seed": int(seed),
        "dtype": str(np.dtype(dtype)), "tile_size": tile_size,
    }
    if albedo_label == "texture":  # a texture is not in the parameters: its digest is
        params["albedo_digest"] = hashlib.sha256(albedo_vec.tobytes()).hexdigest()
    path.parent.mkdir(parents=True, exist_ok=True)
    recipe = _Recipe(path, params, P, albedo_vec, f, G, cut, thr, noise, floor, int(seed),
                     tile_size, dtype, po, memory_limit, exact)
    with stored.disk_full_names(path):
        return _build_resumable(recipe, preview, progress, t_start)


@dataclass(frozen=True)
class _Recipe:
    """Everything a scene build writes from, checked and fixed before anything is
    written (``params`` is its JSON record, compared when a build resumes)."""

    path: Path
    params: dict
    patches: geometry.Patches
    albedo: np.ndarray
    f: np.ndarray
    G: sp.csr_array | None
    cut: float
    threshold: float
    noise: float
    floor: float
    seed: int
    tile_size: int | None
    dtype: str
    pixel_order: PixelOrder
    memory_limit: int
    exact: bool


def _build_resumable(recipe: _Recipe, preview, progress, t_start) -> Scene:
    """The steps of :func:`build` that write, in its resumable work directory."""
    r = recipe
    path, params, P, albedo_vec, f, G = r.path, r.params, r.patches, r.albedo, r.f, r.G
    cut, thr, noise, floor, seed = r.cut, r.threshold, r.noise, r.floor, r.seed
    tile_size, dtype, po, memory_limit, exact = (r.tile_size, r.dtype, r.pixel_order,
                                                 r.memory_limit, r.exact)
    name, n = params["name"], params["n"]
    H, W = params["image_shape"]
    work, resumed = stored.work_directory(path, params)
    tmp = work / "T"
    timings = {}
    t0 = time.perf_counter()
    T = BlockCSRWriter(tmp, (n, n), tile_size=tile_size, dtype=dtype, pixel_order=po,
                       resume=True)
    gt = tmp / GROUND_TRUTH
    if not gt.exists():
        gt.mkdir()
        write_group(gt, {})
    A = stored.write_interreflection(P, albedo_vec, cut, gt / "A", po, T.tile_size,
                                     progress)
    timings["seconds_form_factors"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    times_A = stored.StoredProduct(A, memory_limit)
    T, max_bounces = _write_transport(T, times_A, f, G, thr, noise, floor, seed, name,
                                      progress)
    times_A.release()
    del times_A
    timings["seconds_T"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    stats = _ground_truth_stats(T, A, f, G, memory_limit)
    timings["seconds_stats"] = time.perf_counter() - t0
    summary = {
        **{k: v for k, v in params.items() if k not in ("tile_size", "albedo_digest")},
        "dtype": str(T.dtype), "nnz_T": int(T.nnz), "nnz_A": int(A.nnz),
        "bounces": int(max_bounces), **stats.fields(), "exact": bool(exact),
        "seconds": 0.0, **timings, "resumed": bool(resumed),
        "preview": str(preview_path(path)) if preview else None,
    }
    _commit(tmp, path, f, summary, t_start)
    shutil.rmtree(work, ignore_errors=True)
    scene = load(path)
    if preview:
        _preview(preview_path(path), po.to_images(stats.T1), f"{name} {H}x{W}: T 1, "
                 f"rho(M) = {_radius(stats.rho_M.value)}")
    return scene


def _write_transport(writer, times_A, f, G, thr, noise, floor, seed, name, progress):
    """T = (sum_k A^k) F [G] (paper eq. 6/8) tile row by tile row, truncated at
    ``thr`` and with camera noise, into ``writer`` (the tile rows it still misses).

    Returns
    -------
    (BlockCSR of T, int: the most bounces a tile row needed, 0 for rows resumed)
    """
    fmax = float(f.max()) if len(f) else 0.0
    prune = config.SCENE_PRUNE_FRACTION * thr / fmax if thr > 0 and fmax > 0 else 0.0
    stop = thr if thr > 0 else config.SCENE_NEUMANN_TOL
    max_bounces = 0
    for i in progress_bar(writer.missing_tile_rows, progress=progress,
                          desc=f"{name}: T rows", unit="tile row"):
        r0, r1 = writer.tile_row_range(i)
        rows, k = radiosity.transport_rows(times_A, f, r0, r1, prune=prune, stop=stop,
                                           max_bounces=config.SCENE_MAX_BOUNCES, G=G)
        max_bounces = max(max_bounces, k)
        if thr > 0:
            rows.data[rows.data < thr] = 0.0
            rows.eliminate_zeros()
        if noise > 0 or floor > 0:
            rows = _add_noise(rows, noise, floor, np.random.default_rng([seed, i]))
        writer.write_tile_row(i, rows)
    return writer.finalize(), max_bounces


@dataclass(frozen=True)
class _GroundTruthStats:
    """What a scene's summary says of its transport, measured on the stores.

    Attributes
    ----------
    rho_M, rho_A : SpectralRadius
        Of M = I - T diag(T)^-1 and of A.
    shares : list of float
        Each bounce's share of the light of a white projector image.
    T1 : ndarray, (n,) float64
        T 1, the camera's view of a white projector image (the preview).
    """

    rho_M: SpectralRadius
    rho_A: SpectralRadius
    shares: list
    T1: np.ndarray

    def fields(self) -> dict:
        return {"spectral_radius": _finite(self.rho_M.value),
                "spectral_radius_A": _finite(self.rho_A.value),
                "spectral_radius_uncertainty": _finite(self.rho_M.uncertainty),
                "spectral_radius_A_uncertainty": _finite(self.rho_A.uncertainty),
                "bounce_shares": self.shares}


def _ground_truth_stats(T, A, f, G, memory_limit: int) -> _GroundTruthStats:
    """Spectral radii, bounce shares and T 1 from the stored T and A, one matrix at a
    time held within ``memory_limit`` (streamed from disk beyond it)."""
    n = T.shape[0]
    d = np.asarray(T.diagonal(output_order="matrix"), np.float64)
    times_T = stored.stored_apply(T, memory_limit)
    rho_M = _spectral_radius_T(times_T, d)
    T1 = times_T(np.ones(n))
    del times_T
    times_A = stored.stored_apply(A, memory_limit)
    rho_A = spectral_radius(times_A, n, rtol=config.SCENE_SPECTRAL_RTOL,
                            max_products=config.SCENE_SPECTRAL_MAX_PRODUCTS)
    white = np.ones(n)
    b0 = f * (G @ white if G is not None else white)
    bounces = radiosity.bounce_images(times_A, b0, config.SCENE_SHARE_MAX_BOUNCES,
                                      config.SCENE_SHARE_TOL)
    return _GroundTruthStats(rho_M, rho_A, radiosity.light_shares(bounces), T1)


def _commit(tmp: Path, path: Path, F, summary: dict, t_start: float):
    """Add F to the ground truth of the complete T store built at ``tmp`` (its A is
    there already), record the summary (in the ground-truth group and in T's metadata,
    so ``bigT info`` shows it) and move the scene into place at ``path``."""
    _write_F(tmp / GROUND_TRUTH, F)
    summary["seconds"] = time.perf_counter() - t_start
    write_group(tmp / GROUND_TRUTH, {SCENE_ATTR: summary})
    open_store(tmp).update_metadata(scene=summary)
    move_into_place(tmp, path)


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
    path = Path(os.fspath(path))
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
        "bounce_shares": radiosity.light_shares(bounces),
        "exact": True, "seconds": 0.0,
        "preview": str(preview_path(path)) if preview else None,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_sibling(path)
    try:
        from_scipy(sp.csr_array(T), tmp, tile_size=2, dtype=dtype, image_shape=(2, 2))
        _write_A(tmp, sp.csr_array(A), po, 2)
        _commit(tmp, path, F, summary, t0)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if preview:
        _preview(preview_path(path), T1.reshape(2, 2), "dihedral4 (paper eq. 34): T 1")
    return load(path)


def load(path) -> Scene:
    """Reopen a scene written by :func:`build` (its T store and ground truth).

    Raises StoreError (naming the path) when the store holds no readable ground truth.
    """
    import zarr

    path = Path(os.fspath(path))
    T = open_store(path)
    gt = path / GROUND_TRUTH
    try:
        summary = zarr.open_group(str(gt), mode="r").attrs.asdict()[SCENE_ATTR]
        A = open_store(gt / "A")
        F = np.asarray(zarr.open_array(str(gt / "F"), mode="r")[:], np.float64)
    except BigTError:
        raise
    except (OSError, KeyError, ValueError, zarr.errors.BaseZarrError) as exc:
        raise StoreError(f"no readable scene ground truth ({exc.__class__.__name__}: {exc}); "
                         "was it written by bigT scene?", gt) from None
    if F.shape != (T.shape[0],) or not np.isfinite(F).all():
        raise StoreError("ground-truth F is damaged (wrong length or missing chunks)", gt / "F")
    return Scene(path, T, A, F, T.pixel_order, summary)


def _named(name):
    def make(size=None, path=None, **kwargs) -> Scene:
        return build(name, size, path, **kwargs)

    make.__name__ = name
    make.__qualname__ = name
    make.__doc__ = f"Build the ``{name}`` scene; parameters as :func:`bigT.scenes.builder.build`."
    return make


corner = _named("corner")
convex = _named("convex")
flat = _named("flat")
cornell = _named("cornell")
hemispheres = _named("hemispheres")


def make(name: str, size=None, path=None, **kwargs) -> Scene:
    """Build scene ``name`` (one of :data:`SCENE_NAMES`)."""
    if name == "dihedral4":
        return dihedral4(size, path, **kwargs)
    return build(name, size, path, **kwargs)


__all__ = ["Scene", "SCENE_NAMES", "build", "corner", "convex", "cornell", "dihedral4",
           "exact_inverse_rows", "flat", "hemispheres", "load", "make"]
