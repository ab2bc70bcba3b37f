"""``invert_to_target`` / ``bigT invert --target-error``: the target met on the probes
and on a fresh image checked densely (numpy, T and X read whole), at spectral radii
0.2, 0.5 and 0.9; the report agrees with the store's record; a target below float32's
precision and bad values through the CLI are one-line errors (exit 2). No wall-clock
assertions."""

import json

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

import bigT
from bigT.algorithms.target import (SAFETY, choose_method, decay_rate, first_prune,
                                    grid_floor, invert_to_target, predicted_curve,
                                    truncation_curve)
from bigT.cli import main
from bigT.storage.frames import to_vectors
from bigT.errors import BigTError

# (scene, albedo) -> rho(M) at 24x32 (exact density): 0.197, 0.52, 0.88
SCENES = {0.2: ("corner", 0.5), 0.5: ("cornell", 0.45), 0.9: ("cornell", 0.615)}
TARGET = 1 / 255


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("target-scenes")
    return {rho: bigT.scenes.make(name, size=(24, 32), path=root / f"{name}{albedo}.zarr",
                                  albedo=albedo, preview=False)
            for rho, (name, albedo) in SCENES.items()}


def _fresh_error(T, X, seed) -> float:
    """||T clip(X d) - d|| / ||d|| for a fresh low-pass random image d, dense numpy, d
    scaled so that the exact inverse's projector image peaks at 1 (the scene's gamut;
    module docstring of bigT.algorithms.target)."""
    H, W = T.pixel_order.image_shape
    img = gaussian_filter(np.random.default_rng(seed).standard_normal((H, W)), 2.5)
    img = 0.2 + 0.6 * (img - img.min()) / np.ptp(img)
    d = to_vectors(img[None], T.pixel_order, np.float64)[:, 0]
    Td = T.to_scipy(output_order="matrix").toarray().astype(np.float64)  # d's order
    Xd = X.to_scipy(output_order="matrix").toarray().astype(np.float64)
    d = d / max(1.0, float(np.linalg.solve(Td, d).max()))
    seen = Td @ np.clip(Xd @ d, 0, 1)
    return float(np.linalg.norm(seen - d) / np.linalg.norm(d))


@pytest.mark.parametrize("rho", sorted(SCENES))
def test_target_met_on_probes_and_fresh_images(scenes, rho, tmp_path):
    scene = scenes[rho]
    assert abs(scene.spectral_radius - rho) < 0.1
    out = tmp_path / "X.zarr"
    report = invert_to_target(scene.T, out, TARGET)
    assert report.met and report.error <= SAFETY * TARGET
    assert report.clipped_error <= TARGET  # the probes scaled into the gamut
    X = bigT.open(out)
    for seed in (1, 2):
        assert _fresh_error(scene.T, X, seed) <= TARGET
    # the report is what the store holds, as a fixed run with these values would
    meta = X.metadata["inverse"]
    assert (meta["term"], meta["method"], meta["prune"]) == (
        report.terms, report.method, report.prune)
    assert report.inverse["terms"] == report.terms
    assert abs(report.spectral_radius - scene.spectral_radius) < 0.05
    assert [t.term for t in report.attempts[-1].terms][-1] == report.terms
    assert report.why and report.method == choose_method(report.predicted_terms)[0]


def test_rerun_on_a_store_that_meets_the_target_computes_nothing(scenes, tmp_path):
    """The same target again on the same output: the engine resumes the store and
    hands the held term to the measurement first, which meets the target; no term is
    computed and the store keeps its term."""
    out = tmp_path / "X.zarr"
    first = invert_to_target(scenes[0.2].T, out, TARGET)
    again = invert_to_target(scenes[0.2].T, out, TARGET)
    assert again.met and again.terms == first.terms
    assert again.inverse["resumed_from"] == first.terms
    assert again.inverse["products"] == 0
    assert bigT.open(out).metadata["inverse"]["term"] == first.terms


def test_first_prune_follows_the_rate_of_the_truncation_curve():
    """Pruned entries are carried by every later bounce (their error adds up like
    1 / (1 - rho)), so a slower series starts from a smaller prune: the 1-3 steps of
    the bench's scenes (rho 0.19, 0.52, 0.89; E = 1/255 and 1e-3), and of the dense
    384x512 corner at the default target (rho 0.25 -> 4.5e-6 -> 3e-6)."""
    D = np.ones((10, 2))
    curve = [D * 0.3 * 0.5 ** k for k in range(4)]
    assert decay_rate(curve, D) == pytest.approx(0.5)
    assert decay_rate(curve[:1], D) == pytest.approx(0.3)  # one point: ||M d|| / ||d||
    assert decay_rate([D, D * 1.5], D) == 0.99  # a stalling curve: clamped below 1
    assert [first_prune(1e-3, r) for r in (0.19, 0.52, 0.89)] == [1e-5, 3e-6, 1e-6]
    assert [first_prune(TARGET, r) for r in (0.19, 0.52, 0.89)] == [3e-5, 3e-5, 3e-6]
    assert first_prune(1e-3) == 1e-5  # no rate known: the fastest series' prune
    assert first_prune(3e-4, 0.255) == 3e-6  # by decades it was 1e-6
    # the grid's steps print as written (the fingerprint records them)
    assert [repr(grid_floor(v)) for v in (7.4e-6, 2.9e-6, 3e-6, 1e-5, 9.99e-6)] == [
        "3e-06", "1e-06", "3e-06", "1e-05", "3e-06"]
    # a hair under a power of ten, where the log's tolerance rounds the exponent up
    # (this raised "max() arg is an empty sequence")
    for e in range(-9, 0):
        for eps in (1.5e-9, 5e-10, 1e-12, 0.0, -1e-12, -5e-10):
            v = 10.0 ** e * (1 - eps)
            got = grid_floor(v)
            assert got <= v * (1 + 1e-9) and got * 3.4 > v, (v, got)
    assert grid_floor(1e-5 * (1 - 1.5e-9)) == 3e-6


def test_too_tight_for_float32_is_refused_before_anything_is_written(scenes, tmp_path):
    out = tmp_path / "X.zarr"
    with pytest.raises(BigTError, match="below what T's float32 can show"):
        invert_to_target(scenes[0.2].T, out, 1e-9)
    assert not out.exists()


def test_best_effort_stop_is_reported_not_met(scenes, tmp_path, capsys):
    """A cap of 1 term cannot reach 1e-4 at rho 0.5: the run stops, says so, exits 1."""
    out = tmp_path / "X.zarr"
    report = invert_to_target(scenes[0.5].T, out, 1e-4, max_terms=1)
    assert not report.met and report.terms == 1
    assert "NOT met" in report.summary()
    # term 1 was not worth measuring during the run (far from the target): it is
    # measured once the engine stops at the cap, as is term 0 with a cap of 0
    assert [t.term for t in report.attempts[-1].terms] == [1]
    assert report.attempts[-1].ended == "term cap 1"
    report = invert_to_target(scenes[0.5].T, tmp_path / "X0.zarr", 1e-4, max_terms=0)
    assert not report.met and report.terms == 0
    assert [t.term for t in report.attempts[-1].terms] == [0]


def test_cli_target_error_summary_json_and_bad_values(scenes, tmp_path, capsys):
    T = str(scenes[0.2].path)
    J = tmp_path / "r.json"
    assert main(["invert", T, "-o", str(tmp_path / "X.zarr"), "--target-error", "0.0039",
                 "--no-progress", "--json", str(J)]) == 0
    out = capsys.readouterr().out
    assert "target error 0.0039: met" in out and "chosen: power, prune" in out
    report = json.loads(J.read_text())
    assert report["met"] and report["target"] == 0.0039 and report["why"]
    cases = [(["--target-error", v], "must be a finite number in (0, 1)")
             for v in ("0", "1", "-0.1", "nan", "2", "x")]
    cases += [(["--target-error", "1e-9"], "below what T's float32 can show"),
              (["--target-error", "0.01", "--terms", "3"], "--terms cannot be combined"),
              (["--target-error", "0.01", "--tol", "1e-3"], "--tol cannot be combined"),
              (["--target-error", "0.01", "--prune-operator", "1e-3"],
               "--prune-operator cannot be combined")]
    for extra, message in cases:
        assert main(["invert", T, "-o", str(tmp_path / "Y.zarr"), "--no-progress"]
                    + extra) == 2
        err = capsys.readouterr().err
        lines = [line for line in err.splitlines() if line.strip()]
        assert message in err and len(lines) == 1, err
        assert not (tmp_path / "Y.zarr").exists()


def test_in_memory_search_writes_only_the_terms_it_measures(scenes, tmp_path, monkeypatch):
    from bigT.algorithms import resident
    from bigT.algorithms.engine_path import ENVIRONMENT

    T = scenes[0.5].T  # the power form: terms the search goes past
    monkeypatch.setenv(ENVIRONMENT, "0")
    ooc = invert_to_target(T, tmp_path / "ooc.zarr", TARGET)
    written, real_write = set(), resident._write_row

    def recording_write(attrs, path, block, A):
        written.add(int(path.parent.name[1:]))
        return real_write(attrs, path, block, A)

    monkeypatch.setattr(resident, "_write_row", recording_write)
    monkeypatch.setenv(ENVIRONMENT, "1")
    mem = invert_to_target(T, tmp_path / "mem.zarr", TARGET)
    # the same search, measured terms and inverse
    assert (mem.method, mem.prune, mem.terms) == (ooc.method, ooc.prune, ooc.terms)
    assert [[m.term for m in a.terms] for a in mem.attempts] == [
        [m.term for m in a.terms] for a in ooc.attempts]
    assert mem.error == pytest.approx(ooc.error, rel=1e-4)
    np.testing.assert_allclose(bigT.open(tmp_path / "mem.zarr").to_scipy().toarray(),
                               bigT.open(tmp_path / "ooc.zarr").to_scipy().toarray(),
                               rtol=1e-5, atol=1e-9)
    measured = {m.term for a in mem.attempts for m in a.terms}
    # term 0 is never handed over: the engine asks whether it is read, like any term
    assert written - {0} == measured and len(written - {0}) < mem.terms


def test_the_curve_counts_its_last_point_without_computing_it():
    """The truncation curve of a geometric series (M = I / 2): the point that the last
    step's ratio puts below the goal is counted, not computed, so the count is the
    full curve's with one product fewer."""
    class Halving:
        calls = 0

        def M(self, V):
            Halving.calls += 1
            return 0.5 * V

    D = np.ones((6, 3))
    full = truncation_curve(Halving(), D, 0.1, 200)
    assert [float(np.linalg.norm(P[:, 0]) / np.linalg.norm(D[:, 0])) for P in full] == [
        0.5, 0.25, 0.125, 0.0625]
    Halving.calls = 0
    powers, predicted = predicted_curve(Halving(), D, 0.1, 200)
    assert predicted == len(full) - 1 == 3 and Halving.calls == 3 == len(powers)
    assert predicted_curve(Halving(), D, 0.1, 2)[1] == 2  # the cap bounds the count
    assert predicted_curve(Halving(), D, 0.6, 200)[1] == 0  # M d meets it: F^-1 alone
