"""The build's validation line: T 1's light split into direct and interreflected, and
what the noise floor dropped of a simulated scene's interreflection."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

import bigT
from bigT import scenes
from bigT.acquisition import make_manifest, simulate_captures, write_patterns
from bigT.acquisition.build import build_transport
from bigT.acquisition.validate import (
    LightSplit,
    WhiteCheck,
    check_white,
    dropped_interreflection,
    light_split,
    row_light,
)

GRID = (6, 8)


def _reference_split(A: np.ndarray, seen: np.ndarray, blocks: int = 1) -> tuple[float, float]:
    """(direct, interreflected) of the dense row-major A over ``seen`` rows and columns,
    direct the diagonal (blocks x blocks per pixel)."""
    A = A * np.outer(seen, seen)
    pixel = np.arange(len(A)) // blocks
    direct = A[pixel[:, None] == pixel[None, :]].sum()
    return direct, A.sum() - direct


def test_the_split_of_a_grey_T_in_tile_order(tmp_path):
    rng = np.random.default_rng(1)
    A = sp.random(48, 48, density=0.3, random_state=2).toarray() + np.diag(rng.uniform(1, 2, 48))
    T = bigT.from_scipy(sp.csr_array(A), tmp_path / "T.zarr", image_shape=GRID, tile_size=16,
                        pixel_order="tile-major", image_tile=(2, 4))
    seen = rng.uniform(size=48) > 0.2
    got = light_split(T, row_light(T, seen))
    assert (got.direct, got.interreflected) == pytest.approx(_reference_split(A, seen), rel=1e-5)
    assert got.entries_per_row == pytest.approx(np.count_nonzero(A) / 48)


def test_the_split_of_a_colour_T_counts_each_pixels_block_as_direct(tmp_path):
    rng = np.random.default_rng(3)
    A = sp.random(144, 144, density=0.2, random_state=4).toarray()
    A += np.kron(np.eye(48), rng.uniform(0.2, 1, (3, 3)))  # every pixel's 3x3 block
    T = bigT.from_scipy(sp.csr_array(A), tmp_path / "T.zarr", image_shape=GRID, channels=3,
                        tile_size=24, pixel_order="tile-major", image_tile=(2, 4))
    seen = np.repeat(rng.uniform(size=48) > 0.2, 3)
    got = light_split(T, row_light(T, seen))
    assert (got.direct, got.interreflected) == pytest.approx(
        _reference_split(A, seen, blocks=3), rel=1e-5)


def test_the_dropped_light_is_counted_in_the_scenes_units():
    """Rows of another camera gain each, and half of every row's interreflection cut."""
    rng = np.random.default_rng(5)
    A = rng.uniform(0, 0.02, (10, 10)) + np.diag(rng.uniform(0.5, 1, 10))
    gain = rng.uniform(0.3, 3, 10)
    built = gain[:, None] * np.where(np.eye(10, dtype=bool), A, A / 2)
    rows = [(np.diag(M).copy(), M.sum(axis=1)) for M in (built, A)]
    share, of_all = dropped_interreflection(*rows)
    inter = A.sum() - np.trace(A)
    assert share == pytest.approx(0.5) and of_all == pytest.approx(0.5 * inter / A.sum())


def test_the_line_says_what_the_floor_dropped_and_what_it_costs():
    image = np.zeros(GRID)
    check = WhiteCheck(0.0803, image, image, [0], kept=LightSplit(96.0, 1.0, 3.7),
                       truth=LightSplit(90.0, 2.5, 192.0), dropped_interreflection=0.625,
                       dropped_light=0.017)
    lines = check.describe().splitlines()
    assert len(lines) == 2
    assert "relative error 0.0803 (of the white's light" in lines[0]
    assert "T keeps 3.7 entries per row: direct light 99 %, interreflected 1.0 % of T 1" \
           in lines[1] and "(the scene's T: 192 per row, interreflected 2.7 %)" in lines[1]
    assert lines[1].endswith("the floor dropped 62 % of the interreflected light (1.7 % of "
                             "all light): compensation will not cancel it")
    # real captures: no scene to compare with, the kept split alone
    alone = WhiteCheck(0.0803, image, image, [0], kept=LightSplit(96.0, 1.0, 3.7))
    assert "scene" not in alone.describe() and "dropped" not in alone.describe()


def test_a_simulated_build_compares_with_its_scene(tmp_path):
    """A linear, noiseless simulation with a floor of 0 keeps all of the scene's light;
    a high floor drops most of its interreflection."""
    scene = scenes.corner(size=GRID, path=tmp_path / "scene.zarr", overwrite=True,
                          progress=False, preview=False)
    patterns = tmp_path / "p"
    write_patterns(patterns, make_manifest("brute-force", (12, 16), 2, graycode=True),
                   progress=False)
    simulate_captures(scene.path, patterns, tmp_path / "c", camera=(30, 40), fmt="npy",
                      progress=False)
    dropped = {}
    for floor in (0.0, 0.05):
        out = tmp_path / f"T{floor}.zarr"
        build_transport(patterns, tmp_path / "c", out, floor=floor, progress=False)
        check = check_white(out)
        assert check.truth is not None
        dropped[floor] = check.dropped_interreflection
    assert abs(dropped[0.0]) < 1e-3 and dropped[0.05] > 0.3, dropped
    assert "the floor dropped" in check.describe()
