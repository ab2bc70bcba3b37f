"""Figures bigT draws, matplotlib on its Agg backend, written as PNG: scan lines,
panels side by side, bounce strips. One module for the scenes, acquisition and
compensation layers alike; matplotlib is imported when a figure is drawn, not before.

Every figure is meant to be read without the code: each image panel has a colour bar
or a stated scale, numbers in titles and labels keep their significant figures
(:func:`number`: 0.0002 is never "0.000"), legends sit where they cover no data."""

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


def number(x: float, digits: int = 3) -> str:
    """``x`` to ``digits`` significant figures, for titles and labels: 0.0002 stays
    "0.0002" where a fixed "{:.3f}" would print "0.000", and 12345.6 reads "1.23e+04"."""
    return f"{float(x):.{digits}g}"


def legend_outside(ax, **kwargs) -> None:
    """The axes' legend to their right, outside the data (call before
    ``fig.tight_layout``, which makes room for it)."""
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0,
              **{"fontsize": 8, **kwargs})


def legend_below(ax, ncol: int = 1, **kwargs) -> None:
    """The axes' legend under them, outside the data (for panels side by side, where a
    legend to the right would cover the next panel)."""
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.16), borderaxespad=0.0,
              ncol=ncol, **{"fontsize": 7, **kwargs})


def label_points(ax, xy: Sequence[tuple[float, float]], texts: Sequence[str], *,
                 colors: Sequence | None = None, fontsize: float = 7, **kwargs) -> None:
    """Annotate data points without the labels overlapping one another.

    Each label tries offsets around its point (right-above first, then right-below,
    left, further out) and takes the first whose box meets no label placed before it
    and no other point's marker. The axes' limits and scales must be final (call after
    ``set_xscale`` etc.).

    Parameters
    ----------
    ax : matplotlib Axes
    xy : (x, y) per point, in data coordinates
    texts : one label per point
    colors : one text colour per point (default: black)
    **kwargs : passed to ``ax.annotate``
    """
    from matplotlib.transforms import Bbox  # matplotlib is loaded: the axes exist

    renderer = ax.figure.canvas.get_renderer()
    # offsets in points, nearest first; the last is taken even where it overlaps
    offsets = [(4, 3), (4, -9), (-4, 3), (-4, -9), (4, 12), (4, -18), (-4, 12), (-4, -18),
               (4, 21), (4, -27)]
    colors = colors if colors is not None else ["black"] * len(texts)
    # the markers are obstacles too: a label may not cover another point
    marks = [Bbox.from_bounds(px - 5, py - 5, 10, 10)
             for px, py in ax.transData.transform(np.asarray(xy, dtype=float))]
    placed = []
    for i, ((x, y), text, colour) in enumerate(zip(xy, texts, colors)):
        others = placed + marks[:i] + marks[i + 1:]
        for k, (dx, dy) in enumerate(offsets):
            ann = ax.annotate(text, (x, y), textcoords="offset points", xytext=(dx, dy),
                              ha="left" if dx > 0 else "right", fontsize=fontsize,
                              color=colour, **kwargs)
            box = ann.get_window_extent(renderer).expanded(1.05, 1.1)
            if k == len(offsets) - 1 or not any(box.overlaps(b) for b in others):
                placed.append(box)
                break
            ann.remove()


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
    """Grayscale (H, W) panels in one row on one shared scale [0, vmax] (default: 1 or
    the largest value when some panel exceeds 1), drawn as one colour bar beside the
    row; RGB (H, W, 3) panels, already encoded for display in [0, 1], are shown as they
    are, the figure saying so."""
    plt = pyplot()
    if vmax is None:
        vmax = max(1.0, max(float(np.max(p)) for p in panels))
    H, W = panels[0].shape[:2]
    # constrained layout: the shared colour bar takes its room from the whole row
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels) + 0.9,
                                                      3.2 * H / W + 1.0), squeeze=False,
                             layout="constrained")
    shown = None
    for ax, img, title in zip(axes[0], panels, titles):
        im = ax.imshow(img, cmap="gray", vmin=0.0, vmax=vmax, interpolation="nearest")
        shown = im if np.ndim(img) == 2 else shown
        ax.set_title(title, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    if suptitle:
        fig.suptitle(suptitle, fontsize=10)
    if shown is not None:  # one bar for the row: every grey panel shares its scale
        bar = fig.colorbar(shown, ax=list(axes[0]), fraction=0.03, pad=0.01)
        bar.set_label("intensity (one scale, all panels)", fontsize=8)
    else:
        fig.supxlabel("colour panels: as a screen shows them, sRGB 0 (black) to 1 "
                      "(white), one scale for all", fontsize=8)
    return save_figure(fig, path)


def scan_lines(path, lines: dict, *, title: str, target: float | None = None) -> Path:
    """Centre scan lines as in the paper's Fig. 10: one curve per label."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8.6, 3.6))
    for label, values in lines.items():
        ax.plot(np.arange(len(values)), values, label=label, lw=1.3)
    if target is not None:
        ax.axhline(target, color="k", lw=0.8, ls="--", label="desired")
    ax.set_xlabel("image column (pixels)")
    ax.set_ylabel("intensity (linear light)")
    ax.set_title(title, fontsize=10)
    legend_outside(ax)  # the curves fill the axes: any corner inside would cover one
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return save_figure(fig, path)


def bounce_strip(path, parts: np.ndarray, shares: Sequence[float]) -> Path:
    """b_0 ... b_K and their sum, each from 0 to its own maximum with its colour bar
    (grey; colour parts (K + 2, H, W, 3) are shown sRGB-encoded from 0 to the panel's
    maximum, stated under the row); the remainder, which may be negative, on a diverging
    scale centred on 0 with its colour bar (its channels summed for colour)."""
    plt = pyplot()
    K = parts.shape[0] - 2
    panels = list(parts) + [parts.sum(axis=0)]
    titles = ["direct light (b0)" if k == 0 else f"bounce {k} (b{k})" for k in range(K + 1)]
    titles = [f"{t}: {number(100 * shares[k])}%" for k, t in enumerate(titles)]
    titles += [f"later bounces (remainder): {number(100 * shares[-1])}%",
               "all the light seen (sum)"]
    H, W = parts.shape[1:3]
    colour = parts.ndim == 4
    # constrained layout: each panel's colour bar takes its room from that panel
    fig, axes = plt.subplots(1, len(panels), figsize=(2.7 * len(panels), 2.4 * H / W + 1.0),
                             squeeze=False, layout="constrained")
    for k, (ax, img, title) in enumerate(zip(axes[0], panels, titles)):
        if k == K + 1:  # the remainder: signed
            img = img.sum(axis=-1) if img.ndim == 3 else img
            span = float(np.abs(img).max()) or 1e-12
            shown = ax.imshow(img, cmap="RdBu_r", vmin=-span, vmax=span,
                              interpolation="nearest")
            fig.colorbar(shown, ax=ax, fraction=0.046, pad=0.02)
        elif colour:  # scaled to the panel's maximum, then sRGB-encoded
            hi = float(img.max())
            ax.imshow(encode(np.clip(img / (hi if hi > 0 else 1.0), 0, 1), "srgb"),
                      interpolation="nearest")
            title += f"\nwhite = {number(hi)}"
        else:
            hi = float(img.max())
            shown = ax.imshow(img, cmap="gray", vmin=0.0, vmax=hi if hi > 0 else 1e-12,
                              interpolation="nearest")
            fig.colorbar(shown, ax=ax, fraction=0.046, pad=0.02)
        ax.set_title(title, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    scale = ("colour panels: 0 (black) to the value under each title (white), sRGB-encoded"
             if colour else "each panel on its own scale (its colour bar)")
    fig.suptitle("the light seen, split by bounce (share of all the light in each title); "
                 f"{scale}; remainder: blue negative, red positive", fontsize=9)
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
    fig, axes = plt.subplots(2, len(views), figsize=(2.9 * len(views), 2 * (2.9 * H / W) + 1.4),
                             squeeze=False, layout="constrained")
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
            axes[1, k].set_title(f"ΔE2000: mean {number(np.mean(m))}, 95% under "
                                 f"{number(np.percentile(m, 95))}", fontsize=8)
        else:
            axes[1, k].axis("off")
        for ax in axes[:, k]:
            ax.set_xticks([])
            ax.set_yticks([])
    if suptitle:
        fig.suptitle(suptitle, fontsize=10)
    fig.supxlabel(f"top: one scale for all, linear light 0 (black) to {number(vmax)} (white), "
                  "sRGB-encoded; bottom: ΔE2000 each on its own scale (its colour bar; "
                  "about 1 is the least a person sees)", fontsize=8)
    return save_figure(fig, path)
