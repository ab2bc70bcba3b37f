"""Figures bigT draws, matplotlib on its Agg backend, written as PNG: scan lines,
panels side by side, bounce strips. One module for the scenes, acquisition and
compensation layers alike; matplotlib is imported when a figure is drawn, not before."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from .atomic import atomic_output
from .colour import encode


def pyplot():
    """matplotlib.pyplot on the Agg backend, imported on first use (~0.4 s kept off
    every command that draws nothing)."""
    import matplotlib  # ~0.4 s with pyplot: only when a figure is drawn

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path, dpi: int = 110) -> Path:
    """Write ``fig`` as PNG to ``path`` whole (:func:`bigT.atomic.atomic_output`) and
    close it."""
    path = Path(path)
    try:
        with atomic_output(path, "the figure") as tmp:
            fig.savefig(tmp, dpi=dpi)
    finally:
        pyplot().close(fig)
    return path


def side_by_side(path, panels: Sequence[np.ndarray], titles: Sequence[str], *,
                 vmax: float | None = None, suptitle: str | None = None) -> Path:
    """Grayscale (H, W) panels in one row, one shared scale [0, vmax] (default: 1 or the
    largest value when some panel exceeds 1)."""
    plt = pyplot()
    if vmax is None:
        vmax = max(1.0, max(float(np.max(p)) for p in panels))
    H, W = panels[0].shape[:2]  # an RGB (H, W, 3) panel is shown as it is
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.2 * H / W + 0.8),
                             squeeze=False)
    for ax, img, title in zip(axes[0], panels, titles):
        ax.imshow(img, cmap="gray", vmin=0.0, vmax=vmax, interpolation="nearest")
        ax.set_title(title, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    if suptitle:
        fig.suptitle(suptitle, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


def scan_lines(path, lines: dict, *, title: str, target: float | None = None) -> Path:
    """Centre scan lines as in the paper's Fig. 10: one curve per label."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 3.6))
    for label, values in lines.items():
        ax.plot(np.arange(len(values)), values, label=label, lw=1.3)
    if target is not None:
        ax.axhline(target, color="k", lw=0.8, ls="--", label="desired")
    ax.set_xlabel("column")
    ax.set_ylabel("intensity")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8, loc="best")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return save_figure(fig, path)


def bounce_strip(path, parts: np.ndarray, shares: Sequence[float]) -> Path:
    """b_0 ... b_K and their sum from 0 to each panel's maximum (grey, or RGB for
    colour parts (K + 2, H, W, 3), shown sRGB-encoded); the remainder, which may be
    negative, on a diverging scale centred on 0 with a colour bar (its channels summed
    for colour)."""
    plt = pyplot()
    K = parts.shape[0] - 2
    panels = list(parts) + [parts.sum(axis=0)]
    titles = [f"b{k} {'direct' if k == 0 else 'bounce'} {100 * shares[k]:.3g}%"
              for k in range(K + 1)]
    titles += [f"remainder {100 * shares[-1]:.3g}%", "sum = T l"]
    H, W = parts.shape[1:3]
    fig, axes = plt.subplots(1, len(panels), figsize=(2.4 * len(panels), 2.4 * H / W + 0.7),
                             squeeze=False)
    for k, (ax, img, title) in enumerate(zip(axes[0], panels, titles)):
        if k == K + 1:  # the remainder: signed
            img = img.sum(axis=-1) if img.ndim == 3 else img
            span = float(np.abs(img).max()) or 1e-12
            shown = ax.imshow(img, cmap="RdBu_r", vmin=-span, vmax=span,
                              interpolation="nearest")
            fig.colorbar(shown, ax=ax, fraction=0.046, pad=0.02)
        elif img.ndim == 3:  # colour: scaled to the panel's maximum, then sRGB-encoded
            hi = float(img.max())
            ax.imshow(encode(np.clip(img / (hi if hi > 0 else 1.0), 0, 1), "srgb"),
                      interpolation="nearest")
        else:
            hi = float(img.max())
            ax.imshow(img, cmap="gray", vmin=0.0, vmax=hi if hi > 0 else 1e-12,
                      interpolation="nearest")
        ax.set_title(title, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle("bounce separation (grey: 0 to each panel's maximum; remainder: blue "
                 "negative, red positive, centred on 0)", fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path)


def colour_views(path, views: dict, delta_e: dict, *, suptitle: str | None = None,
                 vmax: float = 1.0) -> Path:
    """Colour images in a row above their CIEDE2000 Delta E maps.

    Parameters
    ----------
    path : str or os.PathLike, the PNG written
    views : dict of title -> (H, W, 3) linear light, shown sRGB-encoded from [0, vmax]
    delta_e : dict of title -> (H, W) Delta E map, drawn under the view of the same
        title, each on its own scale (0 to its 99th percentile, at least 1: a difference
        of about 1 is the least a person sees) with its colour bar; a view without one
        gets an empty cell
    """
    plt = pyplot()
    H, W = next(iter(views.values())).shape[:2]
    fig, axes = plt.subplots(2, len(views), figsize=(2.9 * len(views), 2 * (2.9 * H / W) + 1),
                             squeeze=False)
    for k, (title, img) in enumerate(views.items()):
        axes[0, k].imshow(encode(np.clip(np.asarray(img) / vmax, 0, 1), "srgb"),
                          interpolation="nearest")
        axes[0, k].set_title(title, fontsize=8)
        if title in delta_e:
            m = delta_e[title]
            top = max(1.0, float(np.percentile(m, 99)))
            shown = axes[1, k].imshow(m, cmap="magma", vmin=0, vmax=top,
                                      interpolation="nearest")
            fig.colorbar(shown, ax=axes[1, k], fraction=0.046, pad=0.02)
            axes[1, k].set_title(f"dE2000 mean {np.mean(m):.2f}, p95 "
                                 f"{np.percentile(m, 95):.2f}", fontsize=8)
        else:
            axes[1, k].axis("off")
        for ax in axes[:, k]:
            ax.set_xticks([])
            ax.set_yticks([])
    if suptitle:
        fig.suptitle(suptitle, fontsize=10)
    return save_figure(fig, path)
