"""The scene's preview: T 1, the camera's view of a white projector image, with three
scan lines drawn on it and plotted beside it (paper Fig. 8), drawn through
:mod:`bigT.figures`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..colour import encode
from ..figures import pyplot, save_figure


def draw_preview(path: Path, image: np.ndarray, title: str) -> Path:
    """T 1 (the camera's view of a white projector image) with three horizontal scan
    lines drawn on it and plotted beside it (paper Fig. 8).

    ``image`` is (H, W) grey, or (H, W, 3) linear RGB: shown sRGB-encoded (scaled so
    its brightest value is white), its scan lines plotted per channel."""
    plt = pyplot()
    colour = image.ndim == 3
    rows = distinct_rows(image.reshape(image.shape[0], -1), 3)
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(10, 3.8), gridspec_kw={"width_ratios": [1, 1.4]})
    if colour:
        peak = float(image.max()) or 1.0
        ax0.imshow(encode(np.clip(image / peak, 0.0, 1.0), "srgb"), interpolation="nearest")
    else:
        fig.colorbar(ax0.imshow(image, cmap="gray", vmin=0, interpolation="nearest"), ax=ax0)
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    styles = ("-", "--", ":")
    for k, r in enumerate(rows):
        if colour:  # the line's style names the row, its colour the channel
            ax0.axhline(r, color="white", ls=styles[k], lw=1)
            for c, name in enumerate(("red", "green", "blue")):
                ax1.plot(image[r, :, c], color=f"tab:{name}", ls=styles[k], lw=1.2,
                         label=f"row {r}" if c == 0 else None)
        else:
            ax0.axhline(r, color=colours[k], lw=1)
            ax1.plot(image[r], color=colours[k], lw=1.3, label=f"row {r}")
    ax0.set_title("the camera's view of a white projector image"
                  + (",\nsRGB, its brightest value white" if colour else ""), fontsize=9)
    ax0.set_xticks([])
    ax0.set_yticks([])
    ax1.set_xlabel("image column (pixels)")
    ax1.set_ylabel("intensity (linear light)")
    ax1.set_title("horizontal scan lines", fontsize=9)
    ax1.grid(alpha=0.3)
    ax1.legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path, dpi=100)


def distinct_rows(image: np.ndarray, k: int) -> list[int]:
    """``k`` rows of ``image`` (H, ...) whose profiles differ most, ascending: the centre row,
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

