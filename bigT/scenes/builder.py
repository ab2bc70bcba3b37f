"""Building a synthetic projector-camera scene, written as a bigT store with its ground
truth (:mod:`.ground_truth`), resumably.

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

A colour scene (``colour=True``) runs the same steps on the three bands at once: A holds
the bands' A_k = diag(albedo_k) FF interleaved (index 3 p + k, the form factors computed
once), the series gives the bands' T_k interleaved, and each tile row is mixed by the
rig (:mod:`.rig`: camera sensitivities C_p, projector primaries P_q) before it is
written: T[3 p + i, 3 q + j] = sum_k C_p[i, k] T_k[p, q] P_q[k, j].

The whole scene is written in the hidden work directory ``.NAME.scene-build`` beside
``path`` and moved into place when complete: a failed or interrupted call leaves
``path`` as it was, and the next call with the same parameters resumes from the tile
rows done. The reader is :mod:`.scene`, the preview :mod:`.preview`, the paper's 4x4
example :mod:`.paper_example`.
"""

from __future__ import annotations

import hashlib
import math
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from .. import config
from ..errors import BigTError, InvalidMatrixError, ShapeMismatchError
from ..progress import progress_bar
from ..schedule.memory import return_freed_memory
from ..storage import BlockCSRWriter, ObjectPath, PixelOrder, as_location, check_replaceable
from . import geometry, palette, radiosity, stored
from .catalog import DEFAULT_SIZES, DENSITIES, SCENE_NAMES
from .colouring import ColourParts, resolve_rig
from .statistics import colour_ground_truth_stats, ground_truth_stats
from .paper_example import dihedral4
from .ground_truth import commit, new_ground_truth_group
from .preview import draw_preview, preview_path
from .scene import Scene, format_radius, load


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


def _permuted_patches(name, size, perm: np.ndarray) -> geometry.Patches:
    """The scene's patches in the store's pixel order."""
    return _patches(name, size).take(perm)


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


def build(name: str, size=None, path=None, *, albedo=0.6, density=None, ff_cut=None,
          threshold=None, noise=0.0, noise_floor=None, blur=0.0, seed=0, tile_size=None,
          pixel_order="tile-major", dtype="float32", overwrite=False, preview=True,
          progress=None, memory_limit=None, colour=False, mixing="global",
          rig=None) -> Scene:
    """Build a named scene at ``path`` (see :func:`corner` and friends).

    Parameters
    ----------
    name : {"corner", "convex", "flat", "cornell", "hemispheres"}
    size : (H, W), optional
        Image size; default ``DEFAULT_SIZES[name]``. n = H W (3 H W for colour).
    path : str or os.PathLike
        Directory of the T store (e.g. ``corner.zarr``); the preview PNG goes beside it.
    albedo : float in (0, 1) or (H, W) ndarray; (H, W, 3) ndarray for colour
        Lambertian albedo, one value or a texture (row-major image). For colour, one
        value is the albedo of the white surfaces (in every band; the scene's coloured
        surfaces, :data:`bigT.scenes.palette.PALETTES`, keep theirs), a texture is an
        RGB albedo per pixel.
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
        Seeds the noise (tile row i uses the stream (seed, i)) and the default rig's
        per-pixel variation.
    tile_size : int, optional
        Default ``config.DEFAULT_TILE_SIZE`` (``config.DEFAULT_COLOUR_TILE_SIZE`` for
        colour, where it is a multiple of 3).
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
    colour : bool
        Build an RGB scene (a colour store, ``channels`` 3, index 3 p + c): each band's
        light with its albedo, mixed by the rig. The truncation ``threshold`` applies to
        the bands' entries (so a global mixing factors T exactly), the noise and the
        noise floor to the stored entries, the blur to each band.
    mixing : {"global", "per-pixel"}
        The default rig's colour mixing (colour only): one camera and one projector
        3x3 for every pixel, or varying by ``rig.DEFAULT_VARIATION`` per pixel.
    rig : ColourRig, optional
        The rig (overrides ``mixing``; implies ``colour``).

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
    path = as_location(path)
    if isinstance(path, ObjectPath):  # built on this machine's disk, then put whole
        check_replaceable(path, overwrite)
        local = build(name, size, stored.scratch_path(path), albedo=albedo, density=density,
                      ff_cut=ff_cut, threshold=threshold, noise=noise,
                      noise_floor=noise_floor, blur=blur, seed=seed, tile_size=tile_size,
                      dtype=dtype, pixel_order=pixel_order, memory_limit=memory_limit,
                      preview=preview, progress=progress, overwrite=True, colour=colour,
                      mixing=mixing, rig=rig)
        return stored.publish_remote(local.path, path, preview_path(local.path) if preview
                                     else None, preview_path(path))
    size = tuple(int(s) for s in (DEFAULT_SIZES[name] if size is None else size))
    if len(size) != 2 or min(size) < 1:
        raise ShapeMismatchError(f"size must be (H, W) with H, W >= 1, got {size}")
    floor = 3.0 * float(noise) if noise_floor is None else float(noise_floor)
    _check_nonnegative(noise=noise, noise_floor=floor, blur=blur)
    noise, blur = float(noise), float(blur)
    check_replaceable(path, overwrite)
    rig = resolve_rig(colour, mixing, rig, seed)
    H, W = size
    pixels = H * W
    po = PixelOrder(size, pixel_order, channels=1 if rig is None else 3)
    perm = po.pixel_permutation
    density, cut, thr = _resolve_density(density, ff_cut, threshold, pixels)
    radiosity.check_all_pairs(pixels, cut)

    patches = partial(_permuted_patches, name, size, perm)
    P = patches()
    G = radiosity.gaussian_blur_matrix(size, blur, perm) if blur > 0 else None
    colour_parts = None
    if rig is None:
        albedo_vec, albedo_label = _albedo_vector(albedo, size, perm)
        f = albedo_vec * P.first_bounce_gain()
    else:
        albedo_vec, albedo_label, table = palette.band_albedo(name, albedo, size, P.face, perm)
        f_bands = albedo_vec * P.first_bounce_gain()[:, None]
        colour_parts = ColourParts.of(rig, size, perm, f_bands, table)
        f = f_bands.ravel()  # the bands interleaved, 3 p + k
        G = None if G is None else radiosity.interleave_bands(G)
    # the form factors make the patches again: their ~76 bytes a pixel (630 MB at 4K)
    # are not held while T is multiplied out beside A
    del P
    memory_limit = int(memory_limit or config.SCENE_IN_MEMORY_BYTES)
    exact = thr == 0 and noise == 0 and floor == 0 and blur == 0
    params = {
        "name": name, "image_shape": [H, W], "n": po.n, "pixel_order": po.order,
        "albedo": albedo_label, "density": density, "ff_cut": cut, "threshold": thr,
        "noise": noise, "noise_floor": floor, "blur": blur, "seed": int(seed),
        "dtype": str(np.dtype(dtype)), "tile_size": tile_size,
        **({} if colour_parts is None else colour_parts.record()),
    }
    if albedo_label == "texture":  # a texture is not in the parameters: its digest is
        params["albedo_digest"] = hashlib.sha256(albedo_vec.tobytes()).hexdigest()
    path.parent.mkdir(parents=True, exist_ok=True)
    recipe = _Recipe(path, params, patches, albedo_vec, f, G, cut, thr, noise, floor, int(seed),
                     tile_size, dtype, po, memory_limit, exact, colour_parts)
    with stored.disk_full_names(path):
        return _build_resumable(recipe, preview, progress, t_start)


@dataclass(frozen=True)
class _Recipe:
    """Everything a scene build writes from, checked and fixed before anything is
    written (``params`` is its JSON record, compared when a build resumes)."""

    path: Path
    params: dict
    patches: Callable[[], geometry.Patches]  # made for A only, then let go
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
    colour: ColourParts | None = None


def _build_resumable(recipe: _Recipe, preview, progress, t_start) -> Scene:
    """The steps of :func:`build` that write, in its resumable work directory: A, T, the
    ground truth measured on them, the commit, then the preview."""
    r, params = recipe, recipe.params
    work, resumed = stored.work_directory(r.path, params)
    tmp = work / "T"
    timings = {}
    t0 = time.perf_counter()
    T = BlockCSRWriter(tmp, (params["n"], params["n"]), tile_size=r.tile_size,
                       dtype=r.dtype, pixel_order=r.pixel_order, resume=True)
    gt = new_ground_truth_group(tmp)
    A = stored.write_interreflection(r.patches(), r.albedo, r.cut, gt / "A", r.pixel_order,
                                     T.tile_size, progress)
    timings["seconds_form_factors"] = time.perf_counter() - t0
    return_freed_memory()  # each phase starts from what it holds, not the last one's peak
    t0 = time.perf_counter()
    T, max_bounces = _write_transport(T, A, r, progress)
    timings["seconds_T"] = time.perf_counter() - t0
    return_freed_memory()
    t0 = time.perf_counter()
    if r.colour is None:
        stats = ground_truth_stats(T, A, r.f, r.G, r.memory_limit)
    else:
        stats = colour_ground_truth_stats(T, A, r.f, r.G, r.colour, r.memory_limit)
    timings["seconds_stats"] = time.perf_counter() - t0
    return_freed_memory()  # the statistics' cached tile rows, before the preview's figure
    summary = {
        **{k: v for k, v in params.items() if k not in ("tile_size", "albedo_digest")},
        "dtype": str(T.dtype), "nnz_T": int(T.nnz), "nnz_A": int(A.nnz),
        "bounces": int(max_bounces), **stats.fields(), "exact": bool(r.exact),
        "seconds": 0.0, **timings, "resumed": bool(resumed),
        "preview": str(preview_path(r.path)) if preview else None,
    }
    if r.colour is None:
        commit(tmp, r.path, r.f, summary, t_start)
    else:
        c = r.colour
        commit(tmp, r.path, c.first_bounce, summary, t_start,
               rig_blocks={"camera": c.camera, "projector": c.projector},
               mixing=c.rig.metadata())
    shutil.rmtree(work, ignore_errors=True)
    scene = load(r.path)
    if preview:
        H, W = params["image_shape"]
        draw_preview(preview_path(r.path), r.pixel_order.to_images(stats.T1),
                     f"{params['name']} {H}x{W}, spectral radius rho(M) = {format_radius(stats.rho_M.value)}")
    return scene


def _write_transport(writer, A, recipe: _Recipe, progress):
    """T = (sum_k A^k) F [G] (paper eq. 6/8) tile row by tile row, truncated at the
    recipe's threshold and with its camera noise, into ``writer`` (the tile rows it
    still misses), A held whole within the recipe's memory limit, else streamed.

    Returns
    -------
    (BlockCSR of T, int: the most bounces a tile row needed, 0 for rows resumed)
    """
    times_A = stored.StoredProduct(A, recipe.memory_limit)
    try:
        return _transport_rows(writer, times_A, recipe, progress)
    finally:
        times_A.release()


def _transport_rows(writer, times_A, recipe: _Recipe, progress):
    """:func:`_write_transport`'s loop over the missing tile rows."""
    f, G, thr, noise, floor, seed = (recipe.f, recipe.G, recipe.threshold, recipe.noise,
                                     recipe.floor, recipe.seed)
    name = recipe.params["name"]
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
        if recipe.colour is not None:  # the bands' rows, truncated, mixed by the rig
            c = recipe.colour
            rows = radiosity.mix_bands(rows, c.camera[r0 // 3:r1 // 3], c.projector_matrix)
        if noise > 0 or floor > 0:
            rows = _add_noise(rows, noise, floor, np.random.default_rng([seed, i]))
        writer.write_tile_row(i, rows)
        del rows
        return_freed_memory()  # a tile row's temporaries, a few ms against ~1 s of products
    return writer.finalize(), max_bounces


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


__all__ = ["build", "corner", "convex", "cornell", "flat", "hemispheres", "make"]
