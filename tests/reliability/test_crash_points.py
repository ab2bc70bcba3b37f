"""Every crash point resumes or rolls back (issue #17, item 2; the loops are in
:mod:`crash_checks`).

By default a sample of the kinds of crash point (:func:`crash_harness.kind_of`) is
tried; ``-m slow`` tries one point of every kind for ``invert`` (about 230 of its 2000
mutations) and every point for ``convert --overwrite`` and ``export``.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from crash_checks import check_convert_overwrite, check_export, check_invert  # noqa: E402

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")

#: Default runs try every SAMPLE-th kind of crash point of invert (about 15 of 230).
SAMPLE = 16


def assert_all_recovered(result) -> None:
    assert result.points >= 2 and result.recovered == result.points, (
        f"{len(result.problems)} of {result.points} crash points: {result.problems[:5]}")


@pytest.mark.parametrize("sample", [SAMPLE, pytest.param(1, marks=pytest.mark.slow)])
def test_invert_resumes_bit_identically_after_a_crash(tmp_path, sample):
    result = check_invert(tmp_path, sample)
    assert result.mutations > 500  # every tile's files count: about 2000
    assert_all_recovered(result)


def test_invert_resumes_after_a_crash_while_carrying_tiles(tmp_path):
    """Light only between pixel sets A and B (M bipartite), none at the pixels of tile
    row 3: terms 2 and 3 carry that tile row of X, which their product leaves alone,
    by hard links (a whole row is linked, format 2); a crash at any link resumes to the
    same inverse."""
    rng = np.random.default_rng(3)
    T = np.diag(rng.uniform(1.5, 2.5, 64))
    T[:32, 32:48] = rng.uniform(0, 0.6 / 32, (32, 16))
    T[32:48, :32] = rng.uniform(0, 0.6 / 32, (16, 32))
    result = check_invert(tmp_path, 1, T=T, terms=3, op="link")
    assert result.points >= 4  # the carried tiles of terms 2 and 3, each file kind
    assert_all_recovered(result)


@pytest.mark.parametrize("every_point", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_convert_overwrite_keeps_the_old_store_or_the_new(tmp_path, every_point):
    assert_all_recovered(check_convert_overwrite(tmp_path, SAMPLE // 4, every_point))


@pytest.mark.parametrize("every_point", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_export_replaces_an_existing_file_whole(tmp_path, every_point):
    assert_all_recovered(check_export(tmp_path, 1, every_point))
