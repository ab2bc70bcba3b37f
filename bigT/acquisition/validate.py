"""Is the acquired T a good model of the scene? (paper §6.1.1, Fig. 8)

T 1 (what T predicts the camera sees under an all-white pattern) against the captured
white image reduced to camera super-pixels, with three horizontal scan lines of both
plotted, and the correspondence map drawn as the paper's Fig. 7b. For a colour T, T 1
(every primary lit) against the white capture's R, G and B: the error is over all
three, the scan lines are of their mean.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..figures import pyplot, save_figure
from ..scenes.preview import distinct_rows
from ..storage import open as open_store
from .build import ACQUISITION_KEY, load_camera_response, load_correspondence
from .captures import Captures, grey_view
from .correspondence import Correspondence
from .manifest import read_manifest


@dataclass(frozen=True)
class WhiteCheck:
    """T 1 against the white capture, over the super-pixels seen.

    Attributes
    ----------
    relative_error : float, ||T 1 - w|| / ||w|| (over R, G and B for colour)
    predicted, captured : ndarray, shape grid (grid + (3,) for colour), the two images
        (0 where unseen)
    rows : list of int, the scan lines drawn
    """

    relative_error: float
    predicted: np.ndarray
    captured: np.ndarray
    rows: list[int]


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
    return WhiteCheck(err, predicted, captured, distinct_rows(grey_view(captured), 3))


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
        ax0.imshow(check.captured, cmap="gray", vmin=0, interpolation="nearest")
    captured, predicted = grey_view(check.captured), grey_view(check.predicted)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for k, r in enumerate(check.rows):
        ax0.axhline(r, color=colours[k], lw=1)
        ax1.plot(captured[r], color=colours[k], lw=1.3, label=f"row {r}, captured")
        ax1.plot(predicted[r], color=colours[k], lw=1.1, ls="--", label=f"row {r}, T 1")
    ax0.set_title("captured white (camera super-pixels)", fontsize=9)
    ax0.set_xticks([])
    ax0.set_yticks([])
    ax1.set_xlabel("super-pixel column")
    ax1.set_ylabel("intensity (mean of R, G, B)" if colour else "intensity")
    ax1.grid(alpha=0.3)
    ax1.legend(fontsize=7, ncol=2)
    fig.suptitle(f"T 1 against the captured white image: relative error "
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
