"""The defaults of ``bigT invert`` (issue #30): with no series option a grey T gets the
target error ``config.DEFAULT_TARGET_ERROR``, whose inverse is checked against the
exact inverse (dense numpy) on fresh images at half an 8-bit level; the target picks
the power form's threshold triple; stores made with the older defaults resume, with the
same explicit options or with none. No wall-clock assertions."""

import json

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

import bigT
from bigT import config
from bigT.algorithms.fingerprint import recorded_setting
from bigT.algorithms.first_bounce import resolve_first_bounce
from bigT.algorithms.settings import Thresholds
from bigT.algorithms.target import first_thresholds, invert_to_target
from bigT.cli import main
from bigT.storage.frames import to_vectors

# rho(M) at 24x32 (exact density): corner 0.2, cornell 0.52 (as test_target_error's)
SCENES = {"corner": 0.5, "cornell": 0.45}


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    root = tmp_path_factory.mktemp("default-scenes")
    return {name: bigT.scenes.make(name, size=(24, 32), path=root / f"{name}.zarr",
                                   albedo=albedo, preview=False)
            for name, albedo in SCENES.items()}


def _projector_levels(T, X, seed: int) -> float:
    """max 255 |X d - T^-1 d| for a fresh low-pass image d in [0.2, 0.8], scaled so that
    the exact compensation T^-1 d peaks at 1 (dense numpy, T and X read whole)."""
    H, W = T.pixel_order.image_shape
    img = gaussian_filter(np.random.default_rng(seed).standard_normal((H, W)), 2.0)
    img = 0.2 + 0.6 * (img - img.min()) / np.ptp(img)
    d = to_vectors(img[None], T.pixel_order, np.float64)[:, 0]
    Td = T.to_scipy(output_order="matrix").toarray().astype(np.float64)
    Xd = X.to_scipy(output_order="matrix").toarray().astype(np.float64)
    exact = np.linalg.solve(Td, d)
    scale = 1.0 / max(1.0, float(exact.max()))
    return float(255 * np.abs(Xd @ (d * scale) - exact * scale).max())


def test_the_triple_keeps_its_ratios():
    got = first_thresholds("power", 1e-5)
    assert got.prune == 1e-5
    assert got.feed == pytest.approx(1e-5 * config.TARGET_FEED_RATIO, rel=1e-12)
    assert got.operator == pytest.approx(1e-5 * config.TARGET_OPERATOR_RATIO, rel=1e-12)
    assert f"{got.feed!r}".count("0000") == 0  # 0.0003, as the fingerprint records it
    assert first_thresholds("horner", 1e-5) == Thresholds(1e-5)  # no feed, no operator
    t = Thresholds(1e-5, 3e-4, 3e-5).scaled(0.1)
    assert t == Thresholds(1e-6, 3e-5, 3e-6)  # rounded: 1e-06, not 1.0000000000000002e-06
    assert Thresholds(1e-5).scaled(0.1) == Thresholds(1e-6)  # unset stays unset


@pytest.mark.parametrize("name", sorted(SCENES))
def test_cli_default_is_invisible_at_8_bits(scenes, name, tmp_path, capsys):
    """``bigT invert T -o X`` alone: the target error's run, the threshold triple
    recorded, and fresh images compensated within half a level of the exact inverse."""
    scene = scenes[name]
    out = tmp_path / "X.zarr"
    assert main(["invert", str(scene.path), "-o", str(out), "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "default: the quickest inverse whose error is invisible at 8 bits" in text
    assert f"target error {config.DEFAULT_TARGET_ERROR:g}: met" in text
    X = bigT.open(out)
    meta = X.metadata["inverse"]
    if meta["method"] == "power":
        assert meta["prune_feed"] == pytest.approx(config.TARGET_FEED_RATIO * meta["prune"])
        assert meta["prune_operator"] == pytest.approx(
            config.TARGET_OPERATOR_RATIO * meta["prune"])
    for seed in (1, 2, 3):
        assert _projector_levels(scene.T, X, seed) <= config.INVISIBLE_LEVELS


def test_old_default_store_resumes_with_its_options_or_none(scenes, tmp_path, capsys):
    """A store of the defaults before issue #30 (--terms 4 --prune 1e-5, no feed): the
    same explicit options resume it (nothing computed); no option resumes it with its
    recorded setting (the target measured on it, not a refusal)."""
    T = scenes["corner"]
    out = tmp_path / "old.zarr"
    bigT.stratified_inverse(T.T, out, terms=4, prune=1e-5, progress=False)
    params = json.loads((out / "zarr.json").read_text())["attributes"]
    assert not any("prune_feed" in json.dumps(v) for v in params.values())
    J = tmp_path / "r.json"
    assert main(["invert", str(T.path), "-o", str(out), "--terms", "4", "--prune", "1e-5",
                 "--no-progress", "--json", str(J)]) == 0
    assert json.loads(J.read_text())["products"] == 0
    assert main(["invert", str(T.path), "-o", str(out), "--no-progress", "--json",
                 str(J)]) == 0
    report = json.loads(J.read_text())
    assert (report["prune"], report["prune_feed"], report["prune_operator"]) == (
        1e-5, None, None)
    assert report["inverse"]["resumed_from"] == 4 and report["met"]
    assert "recorded in the store resumed" in report["why"]
    assert bigT.open(out).metadata["inverse"]["prune"] == 1e-5


def test_recorded_setting_only_for_the_same_T_and_first_bounce(scenes, tmp_path):
    corner, cornell = scenes["corner"].T, scenes["cornell"].T
    out = tmp_path / "X.zarr"
    assert recorded_setting(corner, resolve_first_bounce(corner, "diag"), out) is None
    bigT.stratified_inverse(corner, out, terms=1, prune=1e-6, prune_feed=1e-4,
                            prune_operator=1e-5, progress=False)
    got = recorded_setting(corner, resolve_first_bounce(corner, "diag"), out)
    assert got.method == "power" and got.thresholds == Thresholds(1e-6, 1e-4, 1e-5)
    assert recorded_setting(cornell, resolve_first_bounce(cornell, "diag"), out) is None
    assert recorded_setting(corner, resolve_first_bounce(corner, "identity"), out) is None


def test_target_resumes_a_store_of_other_thresholds_and_restarts_scaled(scenes, tmp_path):
    """A store made at a prune too coarse for the target: resumed with its triple
    first, then restarted with the triple scaled down together (ratios kept)."""
    scene = scenes["cornell"]
    out = tmp_path / "X.zarr"
    bigT.stratified_inverse(scene.T, out, terms=2, prune=1e-3, prune_feed=3e-2,
                            prune_operator=3e-3, progress=False)
    report = invert_to_target(scene.T, out, 1e-3)
    first = report.attempts[0]
    assert (first.prune, first.feed, first.operator) == (1e-3, 3e-2, 3e-3)
    assert report.met and len(report.attempts) > 1 and report.restarts
    last = report.attempts[-1]
    assert last.feed / last.prune == pytest.approx(30) and \
        last.operator / last.prune == pytest.approx(3)
