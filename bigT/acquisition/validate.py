"""Is the acquired T a good model of the scene? (paper §6.1.1, Fig. 8)

T 1 (what T predicts the camera sees under an all-white pattern) against the captured
white image reduced to camera super-pixels, with three horizontal scan lines of both
plotted, and the correspondence map drawn as the paper's Fig. 7b. For a colour T, T 1
(every primary lit) against the white capture's R, G and B: the error is over all
three, the scan lines are of their mean.

The check also says what the noise floor kept of the interreflection: T 1's light split
into the direct light (T's diagonal; of a colour T, each pixel's 3x3 diagonal block) and
the interreflected light (every other entry), over the super-pixels seen. Where the
captures are a simulation's (``simulation.json`` names the scene whose T made them), the
same split of the scene's own T says how much of the interreflection the floor dropped:
light the compensation will not cancel. The two are compared row by row relative to
their direct light, which a camera's gain scales alike.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..algorithms.mixing import diagonal_blocks
from ..figures import pyplot, save_figure
from ..scenes.preview import distinct_rows
from ..storage import open as open_store
from .build import ACQUISITION_KEY, load_camera_response, load_correspondence
from .captures import Captures, grey_view
from .correspondence import Correspondence
from .manifest import read_manifest
from .simulate import SIMULATION


@dataclass(frozen=True)
class LightSplit:
    """T 1's light over the super-pixels seen, split by where it comes from.

    Attributes
    ----------
    direct : float, the diagonal's light (of a colour T: the pixels' 3x3 diagonal blocks)
    interreflected : float, the light of every other entry
    entries_per_row : float, stored entries of T over its side
    """

    direct: float
    interreflected: float
    entries_per_row: float

    @property
    def interreflected_share(self) -> float:
        """The interreflected light's share of T 1's."""
        return self.interreflected / max(self.direct + self.interreflected, 1e-300)


@dataclass(frozen=True)
class WhiteCheck:
    """T 1 against the white capture, over the super-pixels seen.

    Attributes
    ----------
    relative_error : float, ||T 1 - w|| / ||w|| (over R, G and B for colour)
    predicted, captured : ndarray, shape grid (grid + (3,) for colour), the two images
        (0 where unseen)
    rows : list of int, the scan lines drawn
    kept : LightSplit, of the built T
    truth : LightSplit or None, of the scene's T a simulation's captures came from
        (restricted to the super-pixels seen, as T is); None for real captures
    dropped_interreflection : float or None
        The share of the scene's interreflected light T lacks (the noise floor's cut,
        and noise); None without a known scene
    dropped_light : float or None, the same light as a share of all the scene's light
    """

    relative_error: float
    predicted: np.ndarray
    captured: np.ndarray
    rows: list[int]
    kept: LightSplit | None = None
    truth: LightSplit | None = None
    dropped_interreflection: float | None = None
    dropped_light: float | None = None

    def describe(self) -> str:
        """One or two lines: what the relative error measures, what T keeps of the
        interreflection and, with a known scene, what the floor dropped and its cost."""
        colour = " (R, G, B)" if self.predicted.ndim == 3 else ""
        line = (f"validation: T 1 against the captured white image{colour}, relative error "
                f"{self.relative_error:.3g} (of the white's light, what T misses or adds)")
        if self.kept is None:
            return line
        k = self.kept
        line += (f"\n  T keeps {_count(k.entries_per_row)} entries per row: direct light "
                 f"{_percent(1 - k.interreflected_share)}, interreflected "
                 f"{_percent(k.interreflected_share)} of T 1")
        if self.truth is None:
            return line
        line += (f" (the scene's T: {_count(self.truth.entries_per_row)} per row, "
                 f"interreflected {_percent(self.truth.interreflected_share)})")
        dropped = self.dropped_interreflection
        if dropped is None:
            return line
        if dropped <= 0.005:
            return line + "; the floor kept all the interreflected light"
        return (line + f"; the floor dropped {_percent(dropped)} of the interreflected "
                f"light ({_percent(self.dropped_light)} of all light): compensation will "
                "not cancel it")


def _count(value: float) -> str:
    """``3.7``, ``54.4``, ``192``: entries per row."""
    return f"{value:.1f}" if value < 100 else f"{value:.0f}"


def _percent(share: float) -> str:
    """``62 %``, ``1.4 %``, ``0.031 %``: whole percents from 10 %, one decimal from 1 %,
    two significant digits below."""
    value = 100 * share
    if abs(value) >= 10:
        return f"{value:.0f} %"
    return f"{value:.1f} %" if abs(value) >= 1 else f"{value:.2g} %"


def check_white(store) -> WhiteCheck:
    """Compare T 1 with the white capture the store was built from (its metadata names
    the pattern and captures folders)."""
    T = open_store(store)
    s = T.metadata[ACQUISITION_KEY]
    manifest = read_manifest(s["patterns"])
    cap = Captures(manifest, Path(s["captures"]), gamma=s["gamma"],
                   black_file=Path(s["black"]) if s["black"] else None,
                   camera_response=load_camera_response(store))
    corr = Correspondence(load_correspondence(store).astype(np.int64), manifest.grid,
                          s["correspondence"])
    order = T.pixel_order
    means = corr.reducer(order)
    w = means(cap.signal(manifest.single("white")))
    t1 = T.matmul(np.ones(T.shape[1]), order="matrix") * means.seen
    err = float(np.linalg.norm(t1 - w) / max(np.linalg.norm(w), 1e-300))
    captured, predicted = order.to_images(w), order.to_images(t1)
    seen = order.to_images(means.seen.astype(np.float64)).ravel() > 0  # row-major
    kept = row_light(T, seen)
    scene = _simulated_scene(Path(s["captures"]), T)
    truth = None if scene is None else row_light(scene, seen)
    dropped = (None, None) if truth is None else dropped_interreflection(kept, truth)
    return WhiteCheck(err, predicted, captured, distinct_rows(grey_view(captured), 3),
                      kept=light_split(T, kept),
                      truth=None if truth is None else light_split(scene, truth),
                      dropped_interreflection=dropped[0], dropped_light=dropped[1])


def row_light(T, seen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each row's light under a white pattern over the columns ``seen``: from its own
    pixel (direct) and in all, 0 on the rows not seen.

    Parameters
    ----------
    T : BlockCSR with a pixel order (the built T, or the scene's, in its own order)
    seen : ndarray of bool, shape (n,), row-major (index 3 p + c of a colour T): the
        order two stores of one grid share

    Returns
    -------
    (direct, total) : two ndarrays of shape (n,), row-major
    """
    order = T.pixel_order
    lit = seen.astype(np.float64)
    total = T.matmul(lit) * lit
    if order.channels == 1:
        direct = T.diagonal() * lit
    else:  # each row's light from its own pixel: the 3x3 diagonal blocks (matrix order)
        blocks = diagonal_blocks(T)
        mine = np.einsum("pcd,pd->pc", blocks, lit[order.permutation].reshape(-1, 3))
        direct = order.to_images(mine.ravel()).ravel() * lit
    return direct, total


def light_split(T, rows: tuple[np.ndarray, np.ndarray]) -> LightSplit:
    """The sums of :func:`row_light`'s ``rows`` of ``T``."""
    direct, total = (float(v.sum()) for v in rows)
    return LightSplit(direct, total - direct, T.nnz / max(T.shape[0], 1))


def dropped_interreflection(kept: tuple[np.ndarray, np.ndarray],
                            truth: tuple[np.ndarray, np.ndarray]) -> tuple[float, float]:
    """The share of the scene's interreflected light the built T lacks, and that light's
    share of all the scene's light.

    A built row is the scene's times the camera's gain on its camera super-pixel (plus
    noise, less what the floor cut): each row is brought back to the scene's units by
    the ratio of the two direct lights, which the floor keeps.

    Parameters
    ----------
    kept, truth : (direct, total), :func:`row_light` of the built T and of the scene's
    """
    (d, t), (d0, t0) = kept, truth
    rows = (d > 0) & (d0 > 0)
    scale = d0[rows] / d[rows]
    inter = float(((t[rows] - d[rows]) * scale).sum())
    inter0 = float((t0[rows] - d0[rows]).sum())
    if inter0 <= 0:
        return 0.0, 0.0
    return 1.0 - inter / inter0, (inter0 - inter) / max(float(t0[rows].sum()), 1e-300)


def _simulated_scene(captures: Path, T):
    """The scene's T whose simulation wrote ``captures``, when its record names one that
    still exists with T's image shape and channels; else None."""
    try:
        scene = Path(json.loads((captures / SIMULATION).read_text())["scene"])
        truth = open_store(scene)
    except (OSError, ValueError, KeyError):  # real captures, or the scene moved away
        return None
    a, b = truth.pixel_order, T.pixel_order
    if a is None or (a.image_shape, a.channels) != (b.image_shape, b.channels):
        return None
    return truth


def plot_white_check(check: WhiteCheck, path) -> Path:
    """Scan lines of T 1 (dashed) and the captured white (solid), as in paper Fig. 8
    (of colour: the image in colour, the scan lines of the mean of R, G, B)."""
    plt = pyplot()
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 3.8), gridspec_kw={"width_ratios": [1, 1.4]})
    colour = check.captured.ndim == 3
    if colour:  # imshow takes RGB in [0, 1]
        ax0.imshow(np.clip(check.captured / max(check.captured.max(), 1e-300), 0, 1),
                   interpolation="nearest")
    else:
        fig.colorbar(ax0.imshow(check.captured, cmap="gray", vmin=0, interpolation="nearest"),
                     ax=ax0)
    captured, predicted = grey_view(check.captured), grey_view(check.predicted)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for k, r in enumerate(check.rows):
        ax0.axhline(r, color=colours[k], lw=1)
        ax1.plot(captured[r], color=colours[k], lw=1.3, label=f"row {r}, captured")
        ax1.plot(predicted[r], color=colours[k], lw=1.1, ls="--", label=f"row {r}, predicted by T")
    ax0.set_title("captured white (camera super-pixels)", fontsize=9)
    ax0.set_xticks([])
    ax0.set_yticks([])
    ax1.set_xlabel("super-pixel column")
    ax1.set_ylabel("intensity (mean of R, G, B)" if colour else "intensity")
    ax1.grid(alpha=0.3)
    ax1.legend(fontsize=7, ncol=2)
    fig.suptitle(f"the white image as T predicts it against as captured: relative error "
                 f"{check.relative_error:.3g}", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path, dpi=100)


def plot_correspondence(labels: np.ndarray, grid: tuple[int, int], path) -> Path:
    """The camera image coloured by the projector super-pixel each pixel belongs to
    (paper Fig. 7b): neighbouring super-pixels get distinct colours, pixels in no group
    are black."""
    plt = pyplot()
    rng = np.random.default_rng(0)
    palette = rng.uniform(0.25, 1.0, size=(grid[0] * grid[1], 3))
    image = np.zeros(labels.shape + (3,))
    inside = labels >= 0
    image[inside] = palette[labels[inside]]
    fig, ax = plt.subplots(figsize=(6, 6 * labels.shape[0] / labels.shape[1] + 0.6))
    ax.imshow(image, interpolation="nearest")
    ax.set_xticks([])
    ax.set_yticks([])
    seen = len(np.unique(labels[inside]))
    ax.set_title(f"camera super-pixels: {seen} of {grid[0] * grid[1]} projector super-pixels "
                 f"seen", fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path, dpi=100)


def figure_paths(store) -> tuple[Path, Path]:
    """(correspondence PNG, validation PNG) beside the store."""
    store = Path(store)
    name = store.name[:-5] if store.name.endswith(".zarr") else store.name
    return store.with_name(f"{name}-correspondence.png"), store.with_name(f"{name}-validation.png")
