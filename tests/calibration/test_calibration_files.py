"""Calibration files as hostile input (one-line errors naming the file, nothing parsed
past a size bound), RAW captures read as linear values, EXIF exposure times."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bigT.calibration import (exposure_time_from_exif, fit_projector_response,
                              load_projector_response, parse_camera_response, read_raw)
from bigT.calibration._files import MAX_JSON_BYTES
from bigT.errors import CalibrationError, ImageError


def good_document() -> dict:
    levels = np.linspace(0.0, 1.0, 17)
    response = fit_projector_response(levels, 0.02 + 0.98 * levels ** 2.2)
    return response.to_document()


def refused(path, match: str) -> str:
    with pytest.raises(CalibrationError) as error:
        load_projector_response(path)
    text = str(error.value)
    assert "\n" not in text and text.startswith(str(path) + ": ")
    assert match in text, text
    return text


def test_a_good_file_loads(tmp_path):
    path = tmp_path / "p.json"
    path.write_text(json.dumps(good_document()))
    assert load_projector_response(path).black[0] == pytest.approx(0.02)


def test_a_huge_file_is_refused_before_parsing(tmp_path):
    path = tmp_path / "huge.json"
    with open(path, "wb") as f:  # sparse: costs no disk
        f.truncate(MAX_JSON_BYTES + 1)
    refused(path, "more than the")


@pytest.mark.parametrize("text, match", [
    ("{", "not a readable JSON file"),
    ("[1, 2]", "the JSON is a list, not an object"),
    ("[" * 100000 + "]" * 100000, "not a readable JSON file"),
    ('{"format": "bigT.camera_response", "version": 1}', "not a bigT.projector_response file"),
    ('{"format": "bigT.projector_response", "version": 9}', "version 9 is not one"),
    ('{"format": "bigT.projector_response", "version": "1"}', 'version "1" is not one'),
])
def test_not_a_response_file(tmp_path, text, match):
    path = tmp_path / "bad.json"
    path.write_text(text)
    refused(path, match)


@pytest.mark.parametrize("field, value, match", [
    ("levels", "0 to 1", "'levels' is not a 1-dimensional list of numbers"),
    ("levels", [True] * 17, "'levels' is not a 1-dimensional list of numbers"),
    ("output", [[0.1, 0.2], [0.3]], "'output' is a ragged list"),
    ("output", {"a": 1}, "'output' is not a 2-dimensional"),
    ("output", [[float("nan")]] * 17, "'output' holds a NaN"),
    ("output", [[1e400]] * 17, "'output' holds a NaN or an infinity"),
    ("output", [[0.5]] * 16, "must both be (17, 1)"),
    ("output", [[1.0 - 0.05 * i] for i in range(17)], "falls or is negative"),
    ("output", [[0.5 * i / 16] for i in range(17)], "must be 1 at level 1"),
    ("channels", ["grey", "grey"], "'channels' must be"),
    ("channels", "grey", "'channels' must be"),
    ("levels", list(np.linspace(0, 1, 17)[::-1]), "must increase strictly"),
    ("levels", [0.0, 1.0] * 3000, "6000 levels"),
])
def test_fields_of_the_wrong_type_or_shape(tmp_path, field, value, match):
    doc = good_document()
    doc[field] = value
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))  # Python writes NaN and Infinity tokens as given
    refused(path, match)


def test_a_missing_field_and_a_missing_file(tmp_path):
    doc = good_document()
    del doc["output"]
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    refused(path, "the field 'output' is missing")
    refused(tmp_path / "absent.json", "no such file")


@pytest.mark.parametrize("make, match", [
    (lambda p: np.save(p, np.linspace(0, 1, 100)), "declares shape (100,)"),
    (lambda p: np.save(p, np.zeros((256, 2))), "declares shape (256, 2)"),
    (lambda p: np.save(p, np.linspace(1, 0, 256)), "falls between codes 0 and 1"),
    (lambda p: np.save(p, np.array([None] * 256, dtype=object)), "cannot read the table"),
    (lambda p: np.save(p, np.array(["a"] * 256)), "numbers are needed"),
    (lambda p: np.save(p, np.full(256, np.nan)), "NaN"),
    (lambda p: p.write_bytes(b"not a numpy file"), "not a camera table"),
])
def test_hostile_camera_tables(tmp_path, make, match):
    path = tmp_path / "curve.npy"
    make(path)
    with pytest.raises(CalibrationError) as error:
        parse_camera_response(str(path))
    text = str(error.value)
    assert "\n" not in text and str(path) in text and match in text, text


def test_a_forged_npy_header_costs_nothing(tmp_path):
    """A 100-byte file declaring a 10^12-entry table is refused from its header."""
    path = tmp_path / "forged.npy"
    header = {"descr": "<f8", "fortran_order": False, "shape": (10 ** 12, 3)}
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(f, header)
    with pytest.raises(CalibrationError, match=r"declares shape \(1000000000000, 3\)"):
        parse_camera_response(str(path))


def test_camera_json_tables_are_checked(tmp_path):
    path = tmp_path / "curve.json"
    base = {"format": "bigT.camera_response", "version": 1, "kind": "table",
            "channels": ["grey"]}
    for table, match in [([[0.5]] * 255 + [[0.1]], "falls between codes 254 and 255"),
                         ([[0.1, 0.2]] * 256, "does not match its 1 channels"),
                         ("x", "'table' is not a 2-dimensional")]:
        path.write_text(json.dumps(dict(base, table=table)))
        with pytest.raises(CalibrationError, match=match):
            parse_camera_response(str(path))
    path.write_text(json.dumps(dict(base, kind="gamma", gamma="2.2")))
    with pytest.raises(CalibrationError, match="'gamma' is not a 0-dimensional"):
        parse_camera_response(str(path))


def test_exposure_time_from_exif(tmp_path):
    from PIL import Image
    from PIL.TiffImagePlugin import IFDRational

    image = Image.fromarray(np.zeros((8, 8, 3), np.uint8))
    exif = Image.Exif()
    exif.get_ifd(0x8769)[33434] = IFDRational(1, 60)
    image.save(tmp_path / "a.jpg", exif=exif)
    assert exposure_time_from_exif(tmp_path / "a.jpg") == pytest.approx(1 / 60)
    image.save(tmp_path / "b.png")
    assert exposure_time_from_exif(tmp_path / "b.png") is None
    with pytest.raises(ImageError, match="no such file"):
        exposure_time_from_exif(tmp_path / "c.jpg")
    (tmp_path / "d.jpg").write_bytes(b"garbage")
    with pytest.raises(ImageError, match="cannot read its EXIF"):
        exposure_time_from_exif(tmp_path / "d.jpg")


def write_dng(path, cfa: np.ndarray) -> None:
    """A minimal uncompressed DNG (RGGB mosaic, identity colour matrix, white 65535)."""
    import tifffile

    tifffile.imwrite(path, cfa, photometric=32803, compression=None, extratags=[
        (33421, "H", 2, (2, 2), True),                  # CFARepeatPatternDim
        (33422, "B", 4, (0, 1, 1, 2), True),            # CFAPattern: R G / G B
        (50706, "B", 4, (1, 4, 0, 0), True),            # DNGVersion
        (50708, "s", 0, "bigT synthetic", True),        # UniqueCameraModel
        (50714, "I", 1, 0, True),                       # BlackLevel
        (50717, "I", 1, 65535, True),                   # WhiteLevel
        (50721, "2i", 9, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1), True),
        (50778, "H", 1, 21, True),                      # CalibrationIlluminant1: D65
    ])


def test_raw_captures_are_linear(tmp_path):
    """LibRaw's output of a synthetic DNG is proportional to the mosaic's values: a
    region 4x brighter reads 4x brighter, a frame at half the light reads half."""
    pytest.importorskip("rawpy")
    pytest.importorskip("tifffile")
    cfa = np.full((32, 48), 8000, np.uint16)
    cfa[:, 24:] = 2000
    write_dng(tmp_path / "a.dng", cfa)
    write_dng(tmp_path / "b.dng", cfa // 2)
    a, b = read_raw(tmp_path / "a.dng"), read_raw(tmp_path / "b.dng")
    assert a.shape == (32, 48, 3) and a.dtype == np.float64 and a.max() <= 1.0
    bright, dim = a[4:-4, 4:20].mean(axis=(0, 1)), a[4:-4, 28:-4].mean(axis=(0, 1))
    np.testing.assert_allclose(bright / dim, 4.0, rtol=0.01)
    np.testing.assert_allclose(a[4:-4, 4:-4] / 2, b[4:-4, 4:-4], atol=2 / 65535)


def test_raw_errors(tmp_path, monkeypatch):
    with pytest.raises(ImageError, match="no such file"):
        read_raw(tmp_path / "absent.dng")
    import sys

    monkeypatch.setitem(sys.modules, "rawpy", None)  # as if it were not installed
    with pytest.raises(ImageError, match="rawpy is not installed: pip install rawpy"):
        read_raw(tmp_path / "absent.dng")
