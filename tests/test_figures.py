"""bigT.figures draws figures a person can read without the code: every image panel
with a colour bar or a stated scale, numbers to significant figures, point labels that
do not cover one another."""

from __future__ import annotations

import numpy as np
import pytest

from bigT import figures


@pytest.fixture
def drawn(monkeypatch):
    """The figures handed to save_figure, kept for the test (and still written)."""
    kept = []
    save = figures.save_figure

    def keep(fig, path, dpi=110):
        kept.append((fig, list(fig.axes)))
        return save(fig, path, dpi)

    monkeypatch.setattr(figures, "save_figure", keep)
    return kept


def _colour_bars(axes) -> int:
    return sum(ax.get_label() == "<colorbar>" for ax in axes)


@pytest.mark.parametrize("x, text", [(0.0002, "0.0002"), (0.000213, "0.000213"),
                                     (1.0, "1"), (12345.6, "1.23e+04"), (0.1234, "0.123")])
def test_numbers_keep_their_significant_figures(x, text):
    assert figures.number(x) == text


def test_grey_panels_share_one_colour_bar(tmp_path, drawn):
    panels = [np.full((8, 10), v) for v in (0.2, 0.5, 1.5)]
    figures.side_by_side(tmp_path / "p.png", panels, ["a", "b", "c"])
    _, axes = drawn[0]
    assert _colour_bars(axes) == 1
    bar = next(ax for ax in axes if ax.get_label() == "<colorbar>")
    assert bar.get_ylim() == pytest.approx((0.0, 1.5))  # the shared scale, 0 to the largest
    assert "one scale" in bar.get_ylabel()


def test_colour_panels_state_their_scale(tmp_path, drawn):
    panels = [np.full((8, 10, 3), v) for v in (0.2, 0.5)]
    figures.side_by_side(tmp_path / "p.png", panels, ["a", "b"])
    fig, axes = drawn[0]
    assert _colour_bars(axes) == 0 and "one scale for all" in fig.get_supxlabel()


def test_every_grey_bounce_panel_has_its_colour_bar(tmp_path, drawn):
    parts = np.random.default_rng(0).random((4, 8, 10))  # b0, b1, b2, remainder
    figures.bounce_strip(tmp_path / "b.png", parts, [0.7, 0.2, 0.0999, 0.0001])
    _, axes = drawn[0]
    assert _colour_bars(axes) == 5  # b0..b2, the remainder and the sum
    titles = [ax.get_title() for ax in axes if ax.get_label() != "<colorbar>"]
    assert titles[-2] == "later bounces (remainder): 0.01%"  # not rounded to 0.00


def test_point_labels_do_not_overlap(tmp_path):
    plt = figures.pyplot()
    fig, ax = plt.subplots(figsize=(4, 3))
    # three points almost on top of one another, as prune 1e-5 with and without feed
    xy = [(1.0, 1.0), (1.01, 1.0), (1.02, 1.001), (3.0, 2.0)]
    ax.scatter(*zip(*xy))
    ax.set_xlim(0, 4)
    ax.set_ylim(0, 3)
    figures.label_points(ax, xy, ["1e-05", "1e-05/0.0001", "1e-05/3e-06", "far"])
    renderer = fig.canvas.get_renderer()
    boxes = [t.get_window_extent(renderer) for t in ax.texts]
    assert len(boxes) == 4
    assert not any(a.overlaps(b) for i, a in enumerate(boxes) for b in boxes[i + 1:])
    plt.close(fig)
