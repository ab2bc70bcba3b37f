"""The simulated nonlinear rig against its defining formulas and noise model."""

from __future__ import annotations

import numpy as np
import pytest

from bigT.calibration import CameraResponse, NonlinearRig
from bigT.errors import CalibrationError


def test_projector_curve():
    """r(0) = black, r(1) = 1, increasing; its slope at 1 is (1 - b) gamma (1 - sigma),
    the shoulder's roll-off; at mid-scale r is the formula's value."""
    rig = NonlinearRig(projector_gamma=2.2, projector_black=0.03, projector_shoulder=0.4)
    v = np.linspace(0.0, 1.0, 10001)
    r = rig.project(v)
    assert r[0] == pytest.approx(0.03) and r[-1] == pytest.approx(1.0)
    assert np.all(np.diff(r) > 0)
    slope = (r[-1] - r[-2]) / (v[-1] - v[-2])
    assert slope == pytest.approx(0.97 * 2.2 * 0.6, rel=1e-3)
    u = 0.5 ** 2.2
    assert rig.project(0.5) == pytest.approx(0.03 + 0.97 * (u + 0.4 * u * (1 - u)))
    colour = NonlinearRig(projector_black=(0.01, 0.02, 0.03))
    np.testing.assert_allclose(colour.project(np.zeros((2, 3))), [[0.01, 0.02, 0.03]] * 2)


def test_capture_is_quantised_seeded_and_saturates_at_the_full_well():
    rig = NonlinearRig(seed=7)
    radiance = np.full((50, 50), 0.2)
    first = rig.capture(radiance, 1.0)
    np.testing.assert_array_equal(first, rig.capture(radiance, 1.0))          # seeded
    assert not np.array_equal(first, rig.capture(radiance, 1.0, frame=1))     # per frame
    assert not np.array_equal(first, NonlinearRig(seed=8).capture(radiance, 1.0))
    np.testing.assert_array_equal(first * 255, np.rint(first * 255))          # 8-bit codes
    assert rig.capture(radiance, 10.0).min() == 1.0                          # 2x full well
    assert rig.to_codes(first).dtype == np.uint8
    assert NonlinearRig(bits=16).to_codes(first).dtype == np.uint16


def test_capture_noise_matches_the_model():
    """Linear 16-bit camera (quantisation negligible): the standard deviation of a flat
    field is sqrt(s / electrons + read^2), within 5% (2500 samples: the estimate's own
    relative error is 1.4%)."""
    rig = NonlinearRig(camera=CameraResponse("linear"), bits=16, full_well_electrons=10000,
                       read_noise=0.002, seed=1)
    for s in (0.01, 0.3):
        image = rig.capture(np.full((50, 50), s), 1.0)
        assert image.mean() == pytest.approx(s, rel=0.01)
        assert image.std() == pytest.approx(np.sqrt(s / 10000 + 0.002 ** 2), rel=0.05)


def test_bad_rigs_are_refused():
    for kwargs in ({"projector_black": 1.0}, {"projector_shoulder": -0.1},
                   {"projector_gamma": 0}, {"bits": 12}, {"read_noise": -1}):
        with pytest.raises(CalibrationError):
            NonlinearRig(**kwargs)
