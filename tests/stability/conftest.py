"""Fixtures of the stability suite (the helpers themselves live in
``stability_helpers``)."""

from __future__ import annotations

import pytest

from stability_helpers import scratch_dir


@pytest.fixture
def work_dir():
    """A scratch directory for one test's stores, on tmpfs when there is one
    (:func:`stability_helpers.scratch_dir`)."""
    with scratch_dir() as path:
        yield path
