"""A scene on disk and its ground truth: :class:`Scene` (what :func:`load` and the
builders return), the exact inverse F^-1 (I - A) tile row by tile row, and the error of
an inverse against it.

For a noise-free scene without truncation (``threshold=0``) and without blur, the
exact inverse is F^-1 (I - A); :func:`exact_inverse_rows` gives it tile row by tile
row, so the error of an inverse can be measured at full scale without any dense
inversion (or on a sample of rows: :meth:`Scene.inverse_error`).

A colour scene's A holds the bands' interreflections (index 3 p + k, :mod:`.rig`), F
its 3x3 diagonal blocks F_p = C_p diag(f_p) P_p; with C = blockdiag(C_p), T = C (I -
A)^-1 C^-1 F, so the exact inverse is F^-1 (I - C A C^-1), again tile row by tile row.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import zarr

from ..errors import BigTError, ShapeMismatchError, StoreError
from ..spectral import spectral_meaning
from ..storage import PixelOrder, as_location, open_zarr
from ..storage import open as open_store
from .ground_truth import GROUND_TRUTH, SCENE_ATTR
from .rig import ColourRig


@dataclass
class Scene:
    """A scene on disk and its ground truth.

    Attributes
    ----------
    path : pathlib.Path
        The T store; the ground truth is in ``path / "ground_truth"``.
    T, A : BlockCSR, shape (n, n)
        Light transport and interreflection, stored in ``pixel_order``; their products,
        ``to_scipy`` and ``diagonal`` speak row-major image vectors like every store's.
        Colour (n = 3 H W): A holds the bands' A_k interleaved, A[3 p + k, 3 q + k] =
        A_k[p, q], without the rig's mixing.
    F_stored : ndarray, (n,) float64; colour (H W, 3, 3)
        True first bounce (diagonal of F; colour: its 3x3 diagonal blocks) in the stored
        order, the order of the stores' tiles, as the ground truth holds it (:attr:`F`
        is the same in row-major pixel order).
    pixel_order : PixelOrder
    summary : dict
        Name, parameters, nnz, spectral radii, bounce shares, timings (JSON).
    camera_stored, projector_stored : ndarray, (H W, 3, 3) float64, or None
        Colour: the rig's C_p and P_q of each pixel, in the stored order (None for grey).
    """

    path: Path
    T: object
    A: object
    F_stored: np.ndarray
    pixel_order: PixelOrder
    summary: dict = field(default_factory=dict)
    camera_stored: np.ndarray | None = None
    projector_stored: np.ndarray | None = None

    @property
    def channels(self) -> int:
        """1 for a grey scene, 3 for colour (T's index 3 p + c)."""
        return getattr(self.T, "channels", 1)

    @property
    def rig(self) -> ColourRig | None:
        """The colour rig (camera sensitivities, projector primaries, per-pixel
        variation) of a colour scene; None for grey."""
        return ColourRig.from_record(self.summary) if self.channels == 3 else None

    @property
    def F(self) -> np.ndarray:
        """True first bounce in row-major pixel order like every vector of the public API:
        grey, the diagonal of F, (n,) float64 (``F.reshape(H, W)`` is its image; pass it
        as ``first_bounce=``); colour, its diagonal blocks, (H W, 3, 3) float64, block
        p = F_p = C_p diag(f_p) P_p for the pixel p = y W + x."""
        if self.pixel_order is None:
            return self.F_stored
        if self.channels == 1:
            return self.pixel_order.to_images(self.F_stored).ravel()
        return _row_major_blocks(self.F_stored, self.pixel_order)

    @property
    def camera(self) -> np.ndarray | None:
        """Colour: the rig's C_p of each pixel, (H W, 3, 3) in row-major pixel order."""
        return None if self.camera_stored is None else \
            _row_major_blocks(self.camera_stored, self.pixel_order)

    @property
    def projector(self) -> np.ndarray | None:
        """Colour: the rig's P_q of each pixel, (H W, 3, 3) in row-major pixel order."""
        return None if self.projector_stored is None else \
            _row_major_blocks(self.projector_stored, self.pixel_order)

    @property
    def bounce_shares_per_channel(self) -> list[list[float]] | None:
        """Colour: each bounce's share of the light the camera sees in channel R, G and
        B (three lists, each adding up to 1) for a white projector image; None for grey."""
        return self.summary.get("bounce_shares_per_channel")

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
        """Tile row ``i`` of F^-1 (I - A) (colour: F^-1 (I - C A C^-1)), shape
        (rows_i, n), float64."""
        return exact_inverse_rows(self.A, self.F_stored, i, self.camera_stored)

    def inverse_error(self, X, sample: int | None = None, seed: int = 0) -> float:
        """||X - F^-1 (I - A)||_F / ||F^-1 (I - A)||_F, tile row by tile row, over
        all rows or a random sample of them.

        Parameters
        ----------
        X : BlockCSR of T's shape and pixel order (any tile size), or ndarray
            An inverse on disk, or the diagonal of a diagonal one in row-major image
            order (e.g. ``1 / T.diagonal()``), (n,); colour: the 3x3 diagonal blocks of
            a block-diagonal one in row-major pixel order, (H W, 3, 3) (e.g.
            ``numpy.linalg.inv(scene.F)``).
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
            "  spectral radius of M = I - T diag(T)^-1 (ground truth): "
            + _radius_text(s, "spectral_radius"),
            "  spectral radius of A (ground truth): " + _radius_text(s, "spectral_radius_A"),
            "  bounce shares of the light of a white image (adding up to 100%): "
            + ", ".join(f"{100 * v:.3g}%" for v in s["bounce_shares"]),
            f"  built in {s['seconds']:.1f} s"
            + (f"; preview {s['preview']}" if s.get("preview") else ""),
            "  exact inverse F^-1 (I - A) " + ("holds" if s["exact"] else
                                               "holds up to truncation/noise/blur"),
        ]
        if s.get("channels", 1) == 3:
            lines[-2:-2] = _colour_lines(s)
            lines[0] = lines[0].replace(f"(n = {s['n']})", f"(n = {s['n']} = 3 x {H * W} "
                                        "pixels), RGB")
            lines[2] = lines[2].replace("T diag(T)^-1 (ground truth)",
                                        "T F^-1 (ground truth; F the 3x3 diagonal blocks of T)")
            lines[-1] = lines[-1].replace("F^-1 (I - A)", "F^-1 (I - C A C^-1)")
        return "\n".join(lines)


def _colour_lines(s: dict) -> list[str]:
    """The lines :meth:`Scene.describe` adds for a colour scene: its rig and the bounce
    shares per channel."""
    mixing = ("global (T's metadata records it)" if s["mixing"] == "global" else
              f"per pixel (C_p, P_q within {100 * s['rig_variation']:g}% of C, P)")
    rows = " / ".join(" ".join(f"{v:.2f}" for v in row) for row in s["rig_camera"])
    cols = " / ".join(" ".join(f"{v:.2f}" for v in row) for row in s["rig_projector"])
    lines = [f"  colour (R, G, B; index 3 p + c): mixing {mixing}",
             f"  camera sensitivities C = [{rows}], projector primaries P = [{cols}]"]
    for name, shares in zip("RGB", s["bounce_shares_per_channel"]):
        lines.append(f"  bounce shares in {name}: " + ", ".join(f"{100 * v:.3g}%"
                                                              for v in shares[:4])
                     + (", ..." if len(shares) > 4 else ""))
    return lines


def _inverse_rows(X, T):
    """``rows(i)``: tile row ``i`` of T's grid of the inverse ``X`` (a store, the (n,)
    row-major diagonal of a diagonal inverse, or the (H W, 3, 3) row-major diagonal
    blocks of a colour one), float64 CSR."""
    if isinstance(X, np.ndarray) and X.ndim == 3:
        return _block_diagonal_rows(X, T)
    if isinstance(X, np.ndarray):
        if X.shape != (T.shape[0],):
            raise ShapeMismatchError(f"a diagonal X needs {T.shape[0]} entries, got {X.shape}")
        diag = np.asarray(X, np.float64)
        if T.pixel_order is not None:
            diag = diag[T.pixel_order.permutation]  # into the stored order of T's rows

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
        # the matrix X represents (a factored colour inverse: its mixing applied)
        return sp.csr_array(X.represented_rows(*T.tile_row_range(i)), dtype=np.float64)
    return rows


def _block_diagonal_rows(X: np.ndarray, T):
    """``rows(i)`` of the block-diagonal inverse whose (H W, 3, 3) blocks ``X`` are in
    row-major pixel order, for T's (colour) grid."""
    order = T.pixel_order
    if order is None or order.channels != 3 or X.shape != (order.pixels, 3, 3):
        raise ShapeMismatchError(f"a block-diagonal X needs (H W, 3, 3) blocks of a colour "
                                 f"scene, got {X.shape}")
    stored = np.asarray(X, np.float64)[order.pixel_permutation]

    def rows(i):
        r0, r1 = T.tile_row_range(i)
        return _blocks_rows(stored[r0 // 3:r1 // 3], r0, T.shape[1])
    return rows


def _blocks_rows(blocks: np.ndarray, r0: int, n: int) -> sp.csr_array:
    """Rows r0 .. r0 + 3 m of the (n, n) block-diagonal matrix whose m (3, 3) blocks from
    row r0 on are ``blocks``."""
    m = len(blocks)
    bsr = sp.bsr_array((blocks, np.arange(m) + r0 // 3, np.arange(m + 1)), shape=(3 * m, n))
    return sp.csr_array(bsr.tocsr())


def exact_inverse_rows(A, F, i: int, camera: np.ndarray | None = None) -> sp.csr_array:
    """Tile row ``i`` of F^-1 (I - A), shape (rows_i, n), float64.

    A : BlockCSR (n, n), the scene's interreflection; F : (n,) first bounce, both in
    matrix order. Colour: F is (n / 3, 3, 3), its diagonal blocks, ``camera`` the
    rig's (n / 3, 3, 3) C_p (matrix order), and the row is that of
    F^-1 (I - C A C^-1) with C = blockdiag(C_p)."""
    n = A.shape[0]
    r0, r1 = A.tile_row_range(i)
    Arows = sp.csr_array(A.get_tile_row(i), dtype=np.float64)
    eye = sp.csr_array((np.ones(r1 - r0), np.arange(r0, r1), np.arange(r1 - r0 + 1)),
                       shape=(r1 - r0, n))
    F = np.asarray(F, np.float64)
    if F.ndim == 1:
        return sp.csr_array(sp.diags_array(1.0 / F[r0:r1]) @ (eye - Arows))
    p0, p1 = r0 // 3, r1 // 3
    camera = np.asarray(camera, np.float64)
    seen = _blocks_rows(camera[p0:p1], r0, n)[:, r0:r1] @ Arows  # C A, rows r0:r1
    seen = sp.csr_array(seen @ _blocks_rows(np.linalg.inv(camera), 0, n))  # ... C^-1
    return sp.csr_array(_blocks_rows(np.linalg.inv(F[p0:p1]), r0, n)[:, r0:r1] @ (eye - seen))


# --- building ----------------------------------------------------------------------------


def load(path) -> Scene:
    """Reopen a scene written by :func:`build` (its T store and ground truth).

    Raises StoreError (naming the path) when the store holds no readable ground truth.
    """
    path = as_location(path)
    T = open_store(path)
    gt = path / GROUND_TRUTH
    try:
        summary = open_zarr(gt).attrs.asdict()[SCENE_ATTR]
        A = open_store(gt / "A")
        F = np.asarray(open_zarr(gt / "F")[:], np.float64)
    except BigTError:
        raise
    except (OSError, KeyError, ValueError, zarr.errors.BaseZarrError) as exc:
        raise StoreError(f"no readable scene ground truth ({exc.__class__.__name__}: {exc}); "
                         "was it written by bigT scene?", gt) from None
    pixels = T.shape[0] // T.channels
    want = (T.shape[0],) if T.channels == 1 else (pixels, 3, 3)
    if F.shape != want or not np.isfinite(F).all():
        raise StoreError("ground-truth F is damaged (wrong length or missing chunks)", gt / "F")
    if T.channels == 1:
        return Scene(path, T, A, F, T.pixel_order, summary)
    blocks = {name: _read_blocks(gt / name, want) for name in ("camera", "projector")}
    return Scene(path, T, A, F, T.pixel_order, summary, blocks["camera"], blocks["projector"])


def _read_blocks(path: Path, shape) -> np.ndarray:
    """A colour scene's (H W, 3, 3) rig blocks from the ground truth at ``path``."""
    try:
        blocks = np.asarray(open_zarr(path)[...], np.float64)
    except (OSError, KeyError, ValueError, zarr.errors.BaseZarrError) as exc:
        raise StoreError(f"no readable rig blocks ({exc.__class__.__name__}: {exc})",
                         path) from None
    if blocks.shape != tuple(shape) or not np.isfinite(blocks).all():
        raise StoreError("the rig's blocks are damaged (wrong shape or missing chunks)", path)
    return blocks


def _row_major_blocks(stored: np.ndarray, order: PixelOrder) -> np.ndarray:
    """(H W, 3, 3) blocks in the stored pixel order -> row-major pixel order."""
    out = np.empty_like(stored)
    out[order.pixel_permutation] = stored
    return out



def format_radius(value) -> str:
    return "undetermined" if value is None else f"{value:.4f}"


def _radius_text(summary: dict, key: str) -> str:
    """``0.2444 +- 3.4e-11, the largest eigenvalue modulus, computed by ARPACK ...``:
    the summary's radius ``key``, its uncertainty (older scenes have none) and what the
    number is. A scene's radii are eigenvalues computed to convergence (dense or
    ARPACK), never the engine's cheaper bracket, so the two may differ by its width."""
    value, uncertainty = summary.get(key), summary.get(f"{key}_uncertainty")
    if value is None:
        return format_radius(value)
    text = format_radius(value) + ("" if uncertainty is None else f" +- {uncertainty:.1e}")
    method = summary.get(f"{key}_method")
    if method is None:  # a scene written before the method was recorded
        return text + ", the largest eigenvalue modulus, computed to convergence"
    return text + ", " + spectral_meaning(method, value, uncertainty)
