"""float32 against float64, term by term, and float32 at its rounding floor.

The same T stored in both precisions: at every term the two inverses differ by a few
float32 ulps times the condition of T (T rounded to float32 moves its inverse by about
u kappa; each term's arithmetic adds a few ulps of its own), and once float32 reaches
its floor the series neither drifts nor trips the divergence check.
"""

from __future__ import annotations

import numpy as np
import pytest

from stability_helpers import (
    UNIT,
    bipartite_matrix,
    first_bounce,
    invert,
    perron_matrix,
    read_dense,
    relative_error,
    term_by_term,
    transport,
    write_store,
)

U32 = UNIT["float32"]


def case(kind, n=24):
    """Perron N at rho 0.5 (cond(T) ~ 4), or the +-rho pair at 0.9 (cond ~ 20)."""
    if kind == "perron":
        return transport(perron_matrix(n, 0.5, seed=3), first_bounce(n, 3))
    return transport(bipartite_matrix(n, 0.9, seed=3), first_bounce(n, 3))


def per_term(work_dir, T, dtype, terms):
    """X_0 .. X_terms of T stored as ``dtype``, each read back in float64."""
    store = write_store(T, work_dir / f"T{dtype}.zarr", dtype=dtype)
    _, Xs = term_by_term(store, work_dir / f"X{dtype}.zarr", terms)
    assert all(X.dtype == np.dtype(dtype) for X in Xs)  # float32 stays float32
    return [X.astype(np.float64) for X in Xs]


#: "A few float32 ulps times the condition": measured 0.03 to 0.24 u32 cond(T).
FEW = 4


def assert_tracks(work_dir, kind):
    """||X32_k - X64_k|| / ||X64_k|| <= FEW u32 cond(T) at every term k: the
    rounding of each term is contracted by the later ones (rho < 1), so it does not
    pile up with k."""
    T = case(kind)
    kappa = np.linalg.cond(T)
    X64 = per_term(work_dir, T, "float64", 6)
    X32 = per_term(work_dir, T, "float32", 6)
    for k, (a, b) in enumerate(zip(X32, X64)):
        assert relative_error(a, b) <= FEW * U32 * kappa, k


def test_float32_tracks_float64_term_by_term(work_dir):
    assert_tracks(work_dir, "perron")


@pytest.mark.slow
def test_float32_tracks_float64_term_by_term_near_singular(work_dir):
    assert_tracks(work_dir, "bipartite")


def assert_floor(work_dir, method, terms):
    """rho = 0.3: float32 reaches its floor (~u32 cond) by term 13; terms later the
    error is still at the floor, and the residual's rounding noise did not stop the
    run as divergent."""
    T = transport(perron_matrix(24, 0.3, seed=4), first_bounce(24, 4))
    kappa = np.linalg.cond(T)
    rep = invert(write_store(T, work_dir / "T.zarr", dtype="float32"), work_dir / "X.zarr",
                 terms, method=method)
    assert rep.stopped == "terms reached" and rep.terms == terms
    X = read_dense(work_dir / "X.zarr")
    assert relative_error(X, np.linalg.inv(T)) <= FEW * U32 * kappa
    assert rep.residual <= FEW * U32 * kappa


def test_float32_at_its_floor_stays_there(work_dir):
    assert_floor(work_dir, "power", 20)


@pytest.mark.slow
@pytest.mark.parametrize("method,terms", [("power", 40), ("horner", 40),
                                          ("newton-schulz", 63)])
def test_float32_at_its_floor_stays_there_long(work_dir, method, terms):
    assert_floor(work_dir, method, terms)
