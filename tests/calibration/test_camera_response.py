"""Camera responses: the spellings --camera-response takes, each kind's curve against
its defining formula, tables from .npy and .json files, and the forward curve the
simulated camera uses."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bigT.calibration import CameraResponse, normalised_codes, parse_camera_response
from bigT.errors import CalibrationError


def test_spellings():
    assert parse_camera_response("linear").kind == "linear"
    assert parse_camera_response("sRGB").describe() == "sRGB"
    gamma = parse_camera_response("gamma:2.2")
    assert (gamma.kind, gamma.gamma, gamma.describe()) == ("gamma", 2.2, "gamma 2.2")
    for bad, problem in [("gamma:x", "G must be a number"), ("gamma:40", "G must be"),
                         ("log", "unknown camera response 'log'"),
                         ("curve.txt", "unknown camera response 'curve.txt'")]:
        with pytest.raises(CalibrationError, match=problem):
            parse_camera_response(bad)


def test_srgb_against_the_standard_values():
    """IEC 61966-2-1: code 0.5 decodes to 0.21404, code 0.04045 to 0.0031308."""
    srgb = CameraResponse("srgb")
    np.testing.assert_allclose(srgb.to_linear(np.array([0.0, 0.04045, 0.5, 1.0])),
                               [0.0, 0.0031308, 0.21404114, 1.0], rtol=1e-5)
    np.testing.assert_allclose(srgb.to_linear(np.uint8(128)), (128 / 255 + 0.055) ** 2.4
                               / 1.055 ** 2.4)


@pytest.mark.parametrize("response", [CameraResponse("linear"), CameraResponse("srgb"),
                                      CameraResponse("gamma", gamma=1.8),
                                      CameraResponse("table", table=np.linspace(0, 1, 256) ** 3)])
def test_encode_inverts_to_linear(response):
    z = np.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(response.encode(response.to_linear(z)), z, atol=1e-9)


def test_integer_codes_and_tables():
    assert normalised_codes(np.uint16(65535)) == 1.0
    assert normalised_codes(np.uint8(51)) == pytest.approx(0.2)
    with pytest.raises(CalibrationError, match="type int32"):
        normalised_codes(np.int32(3))
    table = np.linspace(0.0, 2.0, 256) ** 2
    response = CameraResponse("table", table=table)
    codes = np.arange(256, dtype=np.uint8)
    np.testing.assert_array_equal(response.to_linear(codes), table)
    # a 16-bit capture against an 8-bit table: interpolated between entries
    assert response.to_linear(np.uint16(257 * 10 + 128)) == pytest.approx(
        table[10] + (table[11] - table[10]) * 128 / 257)
    rgb = CameraResponse("table", table=np.stack([table, 2 * table, 3 * table], axis=1))
    image = np.stack([codes] * 3, axis=-1)
    np.testing.assert_array_equal(rgb.to_linear(image)[:, 2], 3 * table)
    with pytest.raises(CalibrationError, match="3-channel camera response"):
        rgb.to_linear(codes)


def test_table_files_round_trip(tmp_path):
    table = np.stack([np.linspace(0, 1, 256) ** g for g in (2.0, 2.2, 2.4)], axis=1)
    np.save(tmp_path / "curve.npy", table)
    from_npy = parse_camera_response(str(tmp_path / "curve.npy"))
    np.testing.assert_array_equal(from_npy.table, table)
    assert from_npy.describe() == "table of 256 codes x 3 channels (curve.npy)"
    from_json = parse_camera_response(str(from_npy.save(tmp_path / "curve.json")))
    np.testing.assert_array_equal(from_json.table, table)
    gamma = parse_camera_response(str(CameraResponse("gamma", gamma=2.4).save(
        tmp_path / "gamma.json")))
    assert gamma.gamma == 2.4
    (tmp_path / "srgb.json").write_text(json.dumps(
        {"format": "bigT.camera_response", "version": 1, "kind": "srgb"}))
    assert parse_camera_response(str(tmp_path / "srgb.json")).kind == "srgb"


def test_kind_and_parameters_must_agree():
    with pytest.raises(CalibrationError, match="needs its G"):
        CameraResponse("gamma")
    with pytest.raises(CalibrationError, match="needs its table"):
        CameraResponse("table")
    with pytest.raises(CalibrationError, match="unknown camera response kind"):
        CameraResponse("log")
