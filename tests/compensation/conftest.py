"""Fixtures of the compensation tests."""

import pytest

from comp_helpers import random_transport


@pytest.fixture(scope="module")
def small_scene():
    H, W = 10, 12
    T, X, F, A = random_transport(H, W)
    return dict(H=H, W=W, T=T, X=X, F=F, A=A)
