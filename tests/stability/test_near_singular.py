"""Near-singular transports: either a clear refusal or a result whose error is reported
correctly, never silent garbage.

Four ways to be near singular: a series that barely converges (rho(M) = 0.999, or
1 - 1e-9 where T itself has condition ~1e9); pixels that are dim in both directions (a
tiny diagonal with a row and column as tiny: harmless, X just grows); a tiny diagonal
next to bright neighbours (M explodes: must be refused); a zero or negative diagonal
(refused), and a dark pixel (zero row and column: left out of the inverse).
"""

from __future__ import annotations

import numpy as np
import pytest

import bigT

from stability_helpers import (
    bipartite_matrix,
    first_bounce,
    invert,
    perron_matrix,
    power_form,
    read_dense,
    relative_residual,
    spectral_radius,
    term_by_term,
    transport,
    write_store,
)

PROBE_FACTOR = 3.0  # the residual estimate's accuracy (test_spectral_sweep.py)


def near_one(kind, gap, n=24, seed=11):
    """T whose M has radius 1 - gap: Perron (T well conditioned) or the +-rho pair
    (cond(T) ~ 1 / gap)."""
    make = perron_matrix if kind == "perron" else bipartite_matrix
    return transport(make(n, 1 - gap, seed), first_bounce(n, seed))


def assert_refusal_is_clear(err, T):
    """A refusal (the exception ``err``) names the radius it estimated, and only a
    radius the truth puts within 1e-6 of 1 may be refused (no convergent series turned
    away for nothing)."""
    assert "spectral radius of M" in str(err)
    d = np.diag(T)
    assert spectral_radius(np.eye(len(d)) - T / d[None, :]) > 1 - 1e-6


def assert_reported_correctly(T, reports, Xs):
    """Every term is eq. 13 of T, and its recorded residual is the true one within the
    probes' accuracy; the radius reported holds the true one in its uncertainty."""
    d = np.diag(T)
    rho = spectral_radius(np.eye(len(d)) - T / d[None, :])
    for k, (rep, X) in enumerate(zip(reports, Xs)):
        np.testing.assert_allclose(X, power_form(T, k), rtol=0, atol=1e-10 * np.abs(X).max())
        true = relative_residual(T, X)
        assert true / PROBE_FACTOR <= rep.history[-1].residual <= true * PROBE_FACTOR
    last = reports[-1]
    assert abs(last.spectral_radius - rho) <= last.spectral_uncertainty + 1e-12


@pytest.mark.parametrize("kind,gap", [("perron", 1e-3), ("bipartite", 1e-3),
                                      ("bipartite", 1e-9), ("perron", 1e-15)])
def test_a_radius_near_one_is_refused_or_reported(work_dir, kind, gap):
    """The series runs (its error reported as it is: ~ no progress in 4 terms) or,
    within rounding of 1, is refused with the number."""
    T = near_one(kind, gap)
    store = write_store(T, work_dir / "T.zarr")
    try:
        reports, Xs = term_by_term(store, work_dir / "X.zarr", 4)
    except bigT.DivergenceError as e:
        assert_refusal_is_clear(e, T)
        assert gap < 1e-12  # only the case that rounding cannot tell from 1
        return
    assert_reported_correctly(T, reports, Xs)


@pytest.mark.slow
@pytest.mark.parametrize("kind,gap", [("perron", 1e-3), ("bipartite", 1e-3),
                                      ("bipartite", 1e-9)])
def test_a_radius_near_one_is_reported_arnoldi(work_dir, kind, gap):
    """The same beyond the dense estimator (n = 300, Arnoldi), 6 terms."""
    T = near_one(kind, gap, n=300)
    store = write_store(T, work_dir / "T.zarr", tile_size=128)
    reports, Xs = term_by_term(store, work_dir / "X.zarr", 6)
    assert_reported_correctly(T, reports, Xs)


def test_dim_pixels_only_scale_the_inverse(work_dir):
    """Rows and columns of 3 pixels scaled by 1e-6 (diagonal 1e-12): T' = D T D, so
    M' = D M D^-1 has the same radius and X' = D^-1 X D^-1, entries up to 1e12.

    The residual I - T' X' = D (I - T X) D^-1 is not invariant: its dim columns grow
    by 1e6, and the report must say so (X' is as accurate entry by entry, but the
    residual and ``tol`` see ~1e5 times more)."""
    T = near_one("perron", 0.5)
    D = np.ones(24)
    D[[2, 11, 19]] = 1e-6
    Td = D[:, None] * T * D[None, :]
    rep = invert(write_store(T, work_dir / "T.zarr"), work_dir / "X.zarr", 5)
    rep_d = invert(write_store(Td, work_dir / "Td.zarr"), work_dir / "Xd.zarr", 5)
    X, Xd = read_dense(work_dir / "X.zarr"), read_dense(work_dir / "Xd.zarr")
    np.testing.assert_allclose(Xd * D[:, None] * D[None, :], X, rtol=1e-12, atol=0)
    assert rep_d.spectral_radius == pytest.approx(rep.spectral_radius, abs=1e-12)
    true = relative_residual(Td, Xd)
    assert true / PROBE_FACTOR <= rep_d.residual <= true * PROBE_FACTOR
    assert rep_d.residual > 1e4 * rep.residual


def test_a_tiny_diagonal_under_bright_neighbours_is_refused(work_dir):
    """T_ii = 1e-8 while pixel i's column keeps light of order 0.1: column i of
    M = I - T F^-1 is ~1e7, the series diverges, and bigT says so with the number."""
    T = near_one("perron", 0.5)
    T[[4, 17], [4, 17]] = 1e-8
    store = write_store(T, work_dir / "T.zarr")
    with pytest.raises(bigT.DivergenceError) as err:
        invert(store, work_dir / "X.zarr", 4)
    assert_refusal_is_clear(err.value, T)
    assert not (work_dir / "X.zarr").exists()


@pytest.mark.parametrize("value,match", [(0.0, "zero entries"), (-0.3, "negative entries")])
def test_a_zero_or_negative_diagonal_is_refused(work_dir, value, match):
    """A lit pixel with diag 0 (or < 0, as an over-subtracted black level leaves it):
    F = diag(T) cannot be inverted; an InvalidMatrixError names the index."""
    T = near_one("perron", 0.5)
    T[7, 7] = value
    with pytest.raises(bigT.InvalidMatrixError, match=f"{match}.*index 7"):
        invert(write_store(T, work_dir / "T.zarr"), work_dir / "X.zarr", 2)


def test_a_dark_pixel_is_left_out(work_dir):
    """Pixel 5 has no light in or out (zero row and column: T singular): it is left
    out, and the others' inverse is eq. 13 of T without it."""
    T = near_one("perron", 0.5)
    T[5, :] = 0
    T[:, 5] = 0
    rep = invert(write_store(T, work_dir / "T.zarr"), work_dir / "X.zarr", 5)
    assert rep.excluded_pixels == 1
    X = read_dense(work_dir / "X.zarr")
    keep = np.arange(24) != 5
    assert not X[5].any() and not X[:, 5].any()
    np.testing.assert_allclose(X[np.ix_(keep, keep)], power_form(T[np.ix_(keep, keep)], 5),
                               rtol=0, atol=1e-12)
