"""T scaled by c from 1e-30 to 1e30: X(cT) = X(T) / c.

M = I - (cT)(cF)^-1 does not depend on c, and pruning acts on the dimensionless terms,
so the inverse must scale exactly: to rounding for a power of ten (c T rounds each
entry once), bit for bit for a power of two (no rounding at all). Below the normal
range (a subnormal diagonal) bigT must refuse, not return garbage.
"""

from __future__ import annotations

import numpy as np
import pytest

import bigT

from stability_helpers import (
    UNIT,
    first_bounce,
    invert,
    perron_matrix,
    read_dense,
    scratch_dir,
    transport,
    write_store,
)

TERMS, PRUNE = 4, 1e-6
DECADES = [10.0**e for e in range(-30, 31, 5) if e]


@pytest.fixture(scope="module")
def matrix():
    """T (rho(M) = 0.5, 24 pixels, entries in [0.03, 2]) and its condition number."""
    T = transport(perron_matrix(24, 0.5, seed=9), first_bounce(24, 9))
    return T, float(np.linalg.cond(T))


@pytest.fixture(scope="module")
def unscaled(matrix):
    """X(T) and its report per dtype, computed once for the module."""
    cache = {}
    with scratch_dir() as work_dir:
        def get(dtype):
            if dtype not in cache:
                cache[dtype] = run(work_dir, matrix[0], dtype, dtype)
            return cache[dtype]
        yield get


def run(work_dir, T, dtype, name):
    """The inverse of T stored as ``dtype`` (read back in float64) and its report; one
    tile (tiling is swept elsewhere, and one tile is twice as fast)."""
    rep = invert(write_store(T, work_dir / f"T{name}.zarr", dtype=dtype, tile_size=32),
                 work_dir / f"X{name}.zarr", TERMS, prune=PRUNE)
    return read_dense(work_dir / f"X{name}.zarr").astype(np.float64), rep


def assert_representable(T, X, c, dtype):
    """c T and X / c stay in ``dtype``'s normal range: otherwise the case is one for
    :func:`test_a_subnormal_diagonal_is_refused`, not for exact scaling."""
    info = np.finfo(dtype)
    for A, s in ((T, c), (X, 1 / c)):
        mags = np.abs(A[A != 0]) * s
        assert mags.min() >= info.tiny and mags.max() <= info.max / 10


def assert_scales(work_dir, matrix, unscaled, c, dtype):
    """X(cT) c equals X(T) to a few ulps times the condition, with the same nonzeros,
    the same spectral radius and the same (dimensionless) residual."""
    T, kappa = matrix
    X, rep = unscaled(dtype)
    assert_representable(T, X, c, dtype)
    Xc, rep_c = run(work_dir, T * c, dtype, "c")
    scale = np.abs(X).max()
    assert np.abs(Xc * c - X).max() <= 4 * (TERMS + 1) * UNIT[dtype] * kappa * scale
    assert np.array_equal(Xc != 0, X != 0)
    assert abs(rep_c.spectral_radius - rep.spectral_radius) <= 16 * UNIT[dtype] * kappa
    assert rep_c.residual == pytest.approx(rep.residual, rel=1e-5 if dtype == "float32" else 1e-12)


@pytest.mark.parametrize("c", [1e-30, 1e30])
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_inverse_scales_by_the_inverse_factor(work_dir, matrix, unscaled, dtype, c):
    """The ends of the range."""
    assert_scales(work_dir, matrix, unscaled, c, dtype)


@pytest.mark.slow
@pytest.mark.parametrize("c", DECADES)
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_inverse_scales_every_five_decades(work_dir, matrix, unscaled, dtype, c):
    assert_scales(work_dir, matrix, unscaled, c, dtype)


@pytest.mark.parametrize("dtype,exp", [("float64", -100), ("float32", 90)])
def test_a_power_of_two_scales_bit_for_bit(work_dir, matrix, unscaled, dtype, exp):
    """c = 2^-100 (float64), 2^90 (float32): no rounding anywhere, so X(cT) c is X(T)
    exactly, and so is every recorded residual."""
    T, _ = matrix
    X, rep = unscaled(dtype)
    Xc, rep_c = run(work_dir, T * 2.0**exp, dtype, "c")
    assert np.array_equal(Xc * 2.0**exp, X)
    assert [h.residual for h in rep_c.history] == [h.residual for h in rep.history]


@pytest.mark.slow
@pytest.mark.parametrize("c", [1e-300, 1e300])
def test_float64_scales_to_1e300(work_dir, matrix, unscaled, c):
    """Far beyond the suite's range, still inside float64's normal range."""
    assert_scales(work_dir, matrix, unscaled, c, "float64")


@pytest.mark.parametrize("dtype,c", [("float32", 1e-39), ("float64", 1e-310)])
def test_a_subnormal_diagonal_is_refused(work_dir, matrix, dtype, c):
    """Below the normal range 1 / F overflows: a BigTError naming T's store, no
    inverse."""
    T, _ = matrix
    with pytest.raises(bigT.BigTError) as err:
        run(work_dir, T * c, dtype, "c")
    assert err.value.path == str(work_dir / "Tc.zarr")
    assert not (work_dir / "Xc.zarr").exists()
