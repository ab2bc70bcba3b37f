"""The out-of-core scene build: A written tile row by tile row, T multiplied against
the stored A within a memory limit (whole or in batches), products with stored
matrices, and an interrupted build resumed from the tile rows it had done."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from bigT import scenes
from bigT.scenes import geometry, radiosity, stored
from bigT.scenes.ground_truth import GROUND_TRUTH
from bigT.storage import PixelOrder

SIZE = (24, 32)
TILE = 128  # 6 tile rows: the stored paths really cut A and T into tiles


def build(path, **kwargs):
    kwargs = {"ff_cut": 5e-4, "threshold": 1e-6, "tile_size": TILE, "preview": False, "progress": False,
              **kwargs}
    return scenes.corner(SIZE, path, **kwargs)


def exact(store) -> sp.csr_array:
    """The store in its matrix order, the order of the permuted geometry here."""
    return sp.csr_array(store.to_scipy(output_order="matrix"), dtype=np.float64)


def test_stored_A_equals_the_in_memory_form_factors(tmp_path):
    po = PixelOrder(SIZE, "tile-major")
    P = geometry.wall_corner(SIZE, concave=True).take(po.permutation)
    albedo = np.linspace(0.3, 0.7, P.n)
    A = stored.write_interreflection(P, albedo, 1e-4, tmp_path / "A", po, TILE)
    assert A.grid[0] == -(-P.n // TILE)
    reference = radiosity.interreflection(radiosity.form_factors(P, 1e-4), albedo)
    assert reference.nnz > 50 * P.n
    diff = exact(A) - reference
    assert abs(diff).max() == 0.0 and exact(A).nnz == reference.nnz


SMALL = 1 << 20  # half of it holds no whole A (~0.9 MB): A's tile rows come in batches


@pytest.mark.parametrize("memory_limit", [1 << 30, SMALL])
def test_transport_rows_against_a_stored_A_equal_those_against_A_in_memory(
        tmp_path, memory_limit):
    sc = build(tmp_path / "c.zarr")
    A_mem = exact(sc.A)
    times_A = stored.StoredProduct(sc.A, memory_limit)
    assert (sc.A.nnz * 12 > memory_limit // 2) == (memory_limit == SMALL)
    for i in (0, 3):
        r0, r1 = sc.T.tile_row_range(i)
        got, k1 = radiosity.transport_rows(times_A, sc.F_stored, r0, r1, prune=1e-9, stop=1e-8,
                                           max_bounces=50)
        want, k2 = radiosity.transport_rows(A_mem, sc.F_stored, r0, r1, prune=1e-9, stop=1e-8,
                                            max_bounces=50)
        assert k1 == k2 > 2
        np.testing.assert_allclose(got.toarray(), want.toarray(), rtol=1e-12, atol=1e-18)


def test_stored_apply_is_the_matrix_product(tmp_path):
    sc = build(tmp_path / "c.zarr")
    V = np.random.default_rng(0).standard_normal((sc.T.shape[0], 3))
    for limit in (1 << 30, 0):  # held whole, and read again for every product
        apply = stored.stored_apply(sc.T, limit)
        np.testing.assert_allclose(apply(V), exact(sc.T) @ V, rtol=1e-12)
        np.testing.assert_allclose(apply(V[:, 0]), exact(sc.T) @ V[:, 0], rtol=1e-12)


def test_a_small_memory_limit_builds_the_same_scene(tmp_path):
    big = build(tmp_path / "big.zarr")
    small = build(tmp_path / "small.zarr", memory_limit=SMALL)
    assert (exact(big.T) != exact(small.T)).nnz == 0
    assert big.summary["spectral_radius"] == pytest.approx(small.summary["spectral_radius"],
                                                           rel=1e-9)
    assert big.summary["bounce_shares"] == pytest.approx(small.summary["bounce_shares"],
                                                         rel=1e-9)


class Interrupt(BaseException):
    """Stands for Ctrl-C or a killed process (not an Exception: nothing may catch it)."""


def interrupt_after(monkeypatch, module, name, calls):
    """Make ``module.name`` raise Interrupt on call number ``calls + 1``; returns the
    list of calls made."""
    real = getattr(module, name)
    made = []

    def wrapped(*args, **kwargs):
        if len(made) == calls:
            raise Interrupt
        made.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(module, name, wrapped)
    return made


@pytest.mark.parametrize("stage", ["A", "T"])
def test_an_interrupted_build_resumes_from_the_tile_rows_done(tmp_path, monkeypatch, stage):
    reference = build(tmp_path / "ref.zarr")
    path = tmp_path / "c.zarr"
    target = ("form_factor_rows", 2) if stage == "A" else ("transport_rows", 4)
    with monkeypatch.context() as m:
        interrupt_after(m, radiosity, *target)
        with pytest.raises(Interrupt):
            build(path)
    assert not path.exists()
    work = tmp_path / ".c.zarr.scene-build"
    assert work.is_dir()
    with monkeypatch.context() as m:
        redone = interrupt_after(m, radiosity, target[0], 10**6)
        scene = build(path)
    n_tiles = reference.T.grid[0]
    # only the tile rows missing were computed again
    assert len(redone) == n_tiles - target[1] if stage == "T" else len(redone) < n_tiles
    assert scene.summary["resumed"] is True and not work.exists()
    assert (exact(scene.T) != exact(reference.T)).nnz == 0
    assert (exact(scene.A) != exact(reference.A)).nnz == 0
    assert scene.summary["spectral_radius"] == pytest.approx(
        reference.summary["spectral_radius"], rel=1e-9)


def test_a_leftover_of_other_parameters_is_started_over(tmp_path, monkeypatch):
    path = tmp_path / "c.zarr"
    with monkeypatch.context() as m:
        interrupt_after(m, radiosity, "transport_rows", 3)
        with pytest.raises(Interrupt):
            build(path, albedo=0.5)
    with monkeypatch.context() as m:
        computed = interrupt_after(m, radiosity, "transport_rows", 10**6)
        scene = build(path, albedo=0.6)
    assert len(computed) == scene.T.grid[0] and scene.summary["resumed"] is False
    fresh = build(tmp_path / "fresh.zarr", albedo=0.6)
    assert (exact(scene.T) != exact(fresh.T)).nnz == 0
    assert (path / GROUND_TRUTH / "A").is_dir()


def test_beyond_the_bracket_size_the_radii_are_brackets_holding_the_eigenvalues(
        tmp_path, monkeypatch):
    """A scene beyond ``config.SCENE_BRACKET_MIN_N`` pixels (here every scene) records
    Collatz-Wielandt brackets of rho(M) and rho(A), which hold numpy's values."""
    from bigT import config

    monkeypatch.setattr(config, "SCENE_BRACKET_MIN_N", 0)
    sc = build(tmp_path / "c.zarr")
    T, A = exact(sc.T).toarray(), exact(sc.A).toarray()
    d = np.diag(T)
    rho_M = np.abs(np.linalg.eigvals(np.eye(len(d)) - T / d[None, :])).max()
    rho_A = np.abs(np.linalg.eigvals(A)).max()
    s = sc.summary
    for got, width, method, want in (
            (s["spectral_radius"], s["spectral_radius_uncertainty"],
             s["spectral_radius_method"], rho_M),
            (s["spectral_radius_A"], s["spectral_radius_A_uncertainty"],
             s["spectral_radius_A_method"], rho_A)):
        assert method == "collatz-wielandt"
        assert 0 < width <= 0.1 * got  # narrow enough to be accepted
        assert got - width <= want <= got + width


def test_the_statistics_cache_what_the_process_does_not_hold_already():
    from bigT import config
    from bigT.scenes import statistics
    from bigT.schedule.memory import resident_bytes

    big = 1 << 40  # far beyond what is held: the share
    assert statistics._cache_bytes(big, 1000) == int(config.SCENE_STATS_CACHE_SHARE * big)
    assert statistics._cache_bytes(resident_bytes() // 2, 1000) == 0  # held already
    held = resident_bytes()
    # 64 MiB to spare beyond the headroom (a share of the limit), less the vectors, drift
    limit = int((held + (64 << 20)) / (1 - config.SCENE_STATS_HEADROOM_SHARE))
    got = statistics._cache_bytes(limit, 1000)
    headroom = int(config.SCENE_STATS_HEADROOM_SHARE * limit)
    assert 0 < got <= limit - held - statistics.STATS_VECTORS * 8 * 1000 - headroom + (8 << 20)
