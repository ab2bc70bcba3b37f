"""Noisy transport: T as a camera captures it, then inverted and used to compensate.

A capture is T + black level + noise; subtracting the black level leaves the noise,
negative wherever T is about zero, and entries under the noise floor are dropped
(stability_helpers.measured_transport). The inverse is then computed from the measured
T~ and applied to a desired image; the camera sees it through the true T. What must
hold at every noise level: finite outputs, X equal to eq. 13 of T~, a compensation
error explained by the noise and the series truncation (two rigorous bounds below),
growing gracefully with the noise, and a refusal where T~'s series diverges.
"""

from __future__ import annotations

import numpy as np
import pytest

import bigT

from stability_helpers import (
    first_bounce,
    invert,
    measured_transport,
    perron_matrix,
    power_form,
    read_dense,
    spectral_radius,
    transport,
    write_store,
)

TERMS = 8
#: One tile: the multi-tile paths are swept elsewhere, and one tile halves the time.
TILE = 256


def scene(H, W, seed=5):
    """A clean T (rho(M) = 0.6, 30 % of the pairs interreflect), its noise pattern and
    a smooth desired image in [0.1, 0.5]."""
    n = H * W
    T = transport(perron_matrix(n, 0.6, seed, density=0.3), first_bounce(n, seed))
    G = np.random.default_rng(seed + 1).standard_normal((n, n))
    yy, xx = np.mgrid[0:H, 0:W]
    desired = 0.3 + 0.2 * np.sin(xx / 2.0) * np.cos(yy / 3.0)
    return T, G, desired


def diverges(Tm):
    """Whether T~'s series diverges (dense truth): a non-positive diagonal, or
    rho(I - T~ diag(T~)^-1) >= 1."""
    d = np.diag(Tm)
    return bool((d <= 0).any()) or spectral_radius(np.eye(len(d)) - Tm / d[None, :]) >= 1


def compensate_once(work_dir, T, Tm, desired, name):
    """Invert T~ and compensate ``desired`` with it (unclipped, to measure the linear
    error). Returns (X dense, projector image, relative error of what T shows)."""
    H, W = desired.shape
    store = write_store(Tm, work_dir / f"T{name}.zarr", image_shape=(H, W), tile_size=TILE)
    invert(store, work_dir / f"X{name}.zarr", TERMS)
    X = read_dense(work_dir / f"X{name}.zarr")
    light = bigT.compensate(work_dir / f"X{name}.zarr", desired, clip=None)
    seen = T @ light.ravel()
    err = np.linalg.norm(seen - desired.ravel()) / np.linalg.norm(desired)
    return X, light, float(err)


def check_level(work_dir, T, Tm, desired, name):
    """Every check of one noise level; returns the compensation error (None when the
    engine refused a divergent T~, which must then be refused)."""
    if diverges(Tm):
        with pytest.raises(bigT.BigTError):
            invert(write_store(Tm, work_dir / f"T{name}.zarr", tile_size=TILE),
                   work_dir / f"X{name}.zarr", TERMS)
        return None
    X, light, err = compensate_once(work_dir, T, Tm, desired, name)
    assert np.isfinite(X).all() and np.isfinite(light).all()
    np.testing.assert_allclose(X, power_form(Tm, TERMS), rtol=0, atol=1e-12 * np.abs(X).max())
    d = desired.ravel()
    # rigorous: T X - I = (T~ X - I) - E X with E = T~ - T
    E = Tm - T
    bound = (np.linalg.norm(np.eye(len(d)) - Tm @ X, 2) + np.linalg.norm(E, 2)
             * np.linalg.norm(X, 2))
    assert err <= bound * (1 + 1e-9)
    # rigorous: the exact inverse of T~ does this well; X differs from it only by the
    # truncation of the series
    exact = np.linalg.norm(T @ np.linalg.solve(Tm, d) - d) / np.linalg.norm(d)
    assert abs(err - exact) <= np.linalg.norm(T, 2) * np.linalg.norm(X - np.linalg.inv(Tm), 2)
    return err


def sweep(work_dir, sigmas, H, W):
    """check_level at every noise level; then the sweep-wide checks: errors grow with
    the noise (monotone to 5 %), and by no more than twice the first-order
    perturbation bound ||E|| ||T^-1|| over the noiseless error."""
    T, G, desired = scene(H, W)
    errors = {}
    for i, sigma in enumerate(sigmas):
        Tm = measured_transport(T, G, sigma)
        if sigma > 0:
            assert (Tm < 0).any()  # the black-level subtraction left negatives
        errors[sigma] = (check_level(work_dir, T, Tm, desired, i), Tm)
    kept = [(s, e, Tm) for s, (e, Tm) in errors.items() if e is not None]
    assert kept[0][0] == 0  # the noiseless T is never refused
    base = kept[0][1]
    for (_, e0, _), (_, e1, _) in zip(kept, kept[1:]):
        assert e1 >= 0.95 * e0
    norm_inv = np.linalg.norm(np.linalg.inv(T), 2)
    for _, e, Tm in kept:
        assert e <= base + 2 * np.linalg.norm(Tm - T, 2) * norm_inv
    return errors


def test_noisy_transport_compensates_gracefully(work_dir):
    """6 x 6 pixels, noise 0 to 30 % of the mean first bounce: 30 % diverges (and is
    refused), 10 % still compensates to ~50 %."""
    errors = sweep(work_dir, [0.0, 1e-3, 1e-2, 1e-1, 0.3], 6, 6)
    assert errors[0.3][0] is None  # this pattern at 30 % makes rho(M~) ~ 1.2
    assert errors[0.0][0] < 0.02  # the 8-term truncation at rho = 0.6


@pytest.mark.slow
def test_noisy_transport_compensates_gracefully_fine_sweep(work_dir):
    """12 x 12 pixels, eight noise levels."""
    sweep(work_dir, [0.0, 1e-4, 1e-3, 3e-3, 1e-2, 3e-2, 1e-1, 0.2, 0.3], 12, 12)


def test_clipped_and_matrix_free_compensation_of_noisy_transport(work_dir):
    """With negative entries in T~: the clipped projector image stays in [0, 1], and
    the matrix-free path (8 passes over T~) gives the explicit path's image."""
    T, G, desired = scene(6, 6)
    Tm = measured_transport(T, G, 0.05)
    store = write_store(Tm, work_dir / "T.zarr", image_shape=(6, 6), tile_size=TILE)
    invert(store, work_dir / "X.zarr", TERMS)
    clipped = bigT.compensate(work_dir / "X.zarr", desired)
    assert np.isfinite(clipped).all() and clipped.min() >= 0 and clipped.max() <= 1
    explicit = bigT.compensate(work_dir / "X.zarr", desired, clip=None)
    free = bigT.compensate(None, desired, clip=None, T=store, terms=TERMS, path="matrix-free")
    np.testing.assert_allclose(free, explicit, rtol=1e-10, atol=1e-12)
