"""bigT.simulate against a dense numpy reference on a small scene."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import bigT
from bigT.compensation import Simulation, SimulationReport, simulate_batches

from comp_helpers import make_store, random_transport

H, W = 10, 12


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    T, X, F, A = random_transport(H, W, seed=3)
    make_store(T, d / "T.zarr", image_shape=(H, W), tile_size=48, pixel_order="tile-major")
    make_store(X, d / "X.zarr", image_shape=(H, W), tile_size=48)
    return d, T.astype(np.float32).astype(np.float64), X.astype(np.float32).astype(np.float64)


def _fluct(v):
    return (v.max() - v.min()) / v.mean()


def _reference(T, X, desired, clip):
    """Dense numpy: l_in, T l_in, T l_desired, row-major (K, H, W)."""
    flat = desired.reshape(len(desired), -1).T  # (n, K)
    l_in = X @ flat
    lo, hi = clip
    low, high = int(np.sum(l_in < lo)), int(np.sum(l_in > hi))
    l_in = np.clip(l_in, lo, hi)
    seen, seen0 = T @ l_in, T @ flat
    back = (lambda v: v.T.reshape(desired.shape))
    return back(l_in), back(seen), back(seen0), low, high


def test_simulate_matches_a_dense_reference(scene):
    d, T, X = scene
    rng = np.random.default_rng(1)
    desired = np.stack([np.full((H, W), 0.55), rng.uniform(0.1, 0.9, (H, W)),
                        np.full((H, W), 0.3)])
    sim = bigT.simulate(d / "X.zarr", desired, d / "T.zarr", clip=(0, 0.8), batch=2)
    assert isinstance(sim, Simulation) and isinstance(sim.report, SimulationReport)
    l_in, seen, seen0, low, high = _reference(T, X, desired, (0, 0.8))
    np.testing.assert_allclose(sim.projector, l_in, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(sim.seen, seen, rtol=1e-4, atol=1e-5)

    r = sim.report
    assert r.frames == 3 and r.path.path == "explicit" and r.pixels == desired.size
    assert (r.clipped_low, r.clipped_high) == (low, high) and high > 0
    assert r.clipped_fraction == pytest.approx((low + high) / desired.size)
    ref = np.linalg.norm(desired)
    assert r.error == pytest.approx(np.linalg.norm(seen - desired) / ref, rel=1e-4)
    assert r.error_uncompensated == pytest.approx(np.linalg.norm(seen0 - desired) / ref,
                                                  rel=1e-4)
    # the two constant frames (0 and 2), averaged; the random one is left out
    const = [0, 2]
    expect = [np.mean([_fluct(seen0[i]) for i in const]), np.mean([_fluct(seen[i]) for i in const]),
              np.mean([_fluct(seen0[i][H // 2]) for i in const]),
              np.mean([_fluct(seen[i][H // 2]) for i in const])]
    f = r.flatness
    assert f.frames == 2
    np.testing.assert_allclose([f.image_uncompensated, f.image_compensated,
                                f.line_uncompensated, f.line_compensated], expect, rtol=1e-4,
                               atol=2e-6)  # compensated: ~1e-7, float32 rounding
    np.testing.assert_allclose(r.first.uncompensated, seen0[0], rtol=1e-4, atol=1e-5)
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.error = 0.0
    assert "0.8" in r.describe() and f"{r.error:.4f} compensated" in r.describe()


def test_simulate_one_image_no_constant_matrix_free(scene):
    d, T, X = scene
    desired = np.random.default_rng(2).uniform(0.2, 0.4, (H, W))
    sim = bigT.simulate(None, desired, d / "T.zarr", path="matrix-free", terms=40, clip=None)
    assert sim.projector.shape == (H, W) and sim.report.flatness is None
    assert sim.report.path.path == "matrix-free" and sim.report.clipped_fraction == 0
    # 40 terms of a series with rho < 0.4: the exact inverse to float32 precision
    l_in, seen, *_ = _reference(T, X, desired[None], (-np.inf, np.inf))
    np.testing.assert_allclose(sim.projector, l_in[0], rtol=1e-3, atol=1e-4)
    assert sim.report.error == pytest.approx(np.linalg.norm(seen[0] - desired)
                                             / np.linalg.norm(desired), abs=1e-4)
    assert "n/a" in sim.report.describe() and "clipped" not in sim.report.describe()


def test_simulate_batches_hands_each_batch_on(scene):
    d, T, X = scene
    frames = np.random.default_rng(4).uniform(0.1, 0.5, (4, H, W))
    got = []
    report = simulate_batches([(["a", "b"], frames[:2]), (["c", "d"], frames[2:])],
                              d / "X.zarr", d / "T.zarr",
                              on_batch=lambda names, l_in, seen: got.append((names, seen)))
    assert [n for n, _ in got] == [["a", "b"], ["c", "d"]] and report.first.name == "a"
    whole = bigT.simulate(d / "X.zarr", frames, d / "T.zarr")
    np.testing.assert_allclose(np.concatenate([s for _, s in got]), whole.seen)
    assert report.error == pytest.approx(whole.report.error)
