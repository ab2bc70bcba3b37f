"""Pattern sets and their manifest, pattern images, and the Gray code against
independent references (a per-pixel bit loop, OpenCV's ordering)."""

import json

import numpy as np
import pytest

from bigT.acquisition import Manifest, make_manifest, pattern_image, read_manifest, write_patterns
from bigT.acquisition.patterns import decode_graycode, gray, gray_to_binary
from bigT.errors import AcquisitionError
from bigT.images import read_image


def test_brute_force_lights_each_superpixel_once_plus_black_and_white():
    m = make_manifest("brute-force", (6, 8), 2)
    assert m.grid == (3, 4) and m.n == 12
    kinds = [p.kind for p in m.patterns]
    assert kinds[:2] == ["black", "white"] and kinds.count("superpixel") == 12
    total = sum(pattern_image(m, p) for p in m.of_kind("superpixel"))
    assert np.array_equal(total, np.ones((6, 8)))  # a partition of the projector
    p5 = m.of_kind("superpixel")[5]  # grid (1, 1): rows 2-3, cols 2-3
    img = pattern_image(m, p5)
    assert img[2:4, 2:4].all() and img.sum() == 4


def test_stripes_light_one_band_each():
    m = make_manifest("stripes", (6, 8), 2)
    rows, cols = m.of_kind("row-stripe"), m.of_kind("col-stripe")
    assert [p.band for p in rows] == [0, 1, 2] and [p.band for p in cols] == [0, 1, 2, 3]
    assert np.array_equal(pattern_image(m, rows[1]).nonzero()[0], np.repeat([2, 3], 8))
    assert sum(pattern_image(m, p) for p in cols).min() == 1


def test_gray_code_round_trip_and_one_bit_between_neighbours():
    x = np.arange(1000)
    g = gray(x)
    assert np.array_equal(gray_to_binary(g, 10), x)
    assert all(bin(int(d)).count("1") == 1 for d in g[1:] ^ g[:-1])


def test_graycode_patterns_follow_opencv_order_msb_first_each_with_its_inverse():
    m = make_manifest("graycode", (8, 20), 1)
    gc = m.of_kind("graycode")
    # OpenCV: ceil(log2(width)) column patterns, then ceil(log2(height)) row patterns
    assert [(p.axis, p.bit, p.inverted) for p in gc[:4]] == [
        ("col", 0, False), ("col", 0, True), ("col", 1, False), ("col", 1, True)]
    assert sum(p.axis == "col" for p in gc) == 2 * 5 and sum(p.axis == "row" for p in gc) == 2 * 3
    # a per-pixel reference: bit b (MSB first) of gray(column)
    for p in gc:
        img = pattern_image(m, p)
        coord = np.arange(20) if p.axis == "col" else np.arange(8)
        nbits = 5 if p.axis == "col" else 3
        expect = np.array([(int(c) ^ (int(c) >> 1)) >> (nbits - 1 - p.bit) & 1 for c in coord],
                          bool)
        line = img[0, :] if p.axis == "col" else img[:, 0]
        assert np.array_equal(line.astype(bool), expect ^ bool(p.inverted))


def test_decoding_the_patterns_themselves_gives_every_pixel_its_superpixel():
    m = make_manifest("graycode", (12, 20), 2)
    labels = decode_graycode(m, lambda p: pattern_image(m, p))
    rows, cols = np.meshgrid(np.arange(12) // 2, np.arange(20) // 2, indexing="ij")
    assert np.array_equal(labels, rows * 10 + cols)


def test_decoding_leaves_shadows_and_ambiguous_pixels_out():
    m = make_manifest("graycode", (4, 4), 1)

    def read(p):
        img = pattern_image(m, p)
        img[0, 0] = 0.0  # in shadow: white == black
        img[1, 1] = 0.5  # every pattern equals its inverse
        return img

    labels = decode_graycode(m, read)
    assert labels[0, 0] == -1 and labels[1, 1] == -1 and (labels >= 0).sum() == 14


def _grid_labels(h, w, s):
    rows, cols = np.meshgrid(np.arange(h) // s, np.arange(w) // s, indexing="ij")
    return rows * (w // s) + cols


@pytest.mark.parametrize("black, contrast, noise", [
    (0.01, 0.04, 0.001),    # dim: under OpenCV's 40/255, all shadow with its thresholds
    (0.002, 0.01, 0.0002),  # dimmer still, a quiet camera
    (0.05, 0.85, 0.01),     # bright and noisy: decoded as before
])
def test_decoding_thresholds_are_relative_to_the_noise_and_the_contrast(black, contrast,
                                                                          noise):
    m = make_manifest("graycode", (12, 20), 2)
    rng = np.random.default_rng(1)

    def read(p):
        return black + contrast * pattern_image(m, p) + rng.normal(0, noise, (12, 20))

    labels = decode_graycode(m, read, noise=noise)
    assert np.array_equal(labels, _grid_labels(12, 20, 2))


def test_decoding_leaves_noise_and_interreflected_light_out():
    """A pixel whose contrast is within the noise is a shadow; one whose pattern and
    inverse differ by a small share of its contrast (light from the surroundings,
    nearly even under fine stripes) is ambiguous."""
    m = make_manifest("graycode", (4, 4), 1)
    rng = np.random.default_rng(2)

    def read(p):
        img = 0.01 + 0.5 * pattern_image(m, p)
        img[0, 0] = 0.01 + (0.004 if p.kind == "white" else 0.0)  # 2.8 sigma of contrast
        img[1, 1] = 0.2 + 0.03 * pattern_image(m, p)[1, 1]  # 7 % of a contrast of 0.45
        if p.kind == "white":
            img[1, 1] = 0.65
        return img + rng.normal(0, 0.001, (4, 4))

    labels = decode_graycode(m, read, noise=0.001)
    assert labels[0, 0] == -1 and labels[1, 1] == -1 and (labels >= 0).sum() == 14


def test_written_patterns_and_manifest_read_back(tmp_path):
    m = make_manifest("stripes", (12, 16), 1, graycode=True)
    path = write_patterns(tmp_path, m, progress=False)
    assert read_manifest(tmp_path) == m and read_manifest(path) == m
    d = json.loads(path.read_text())
    assert d["projector"] == [12, 16] and d["superpixel"] == 1 and d["method"] == "stripes"
    for p in m.patterns:
        assert np.array_equal(read_image(tmp_path / p.file), pattern_image(m, p))


def test_a_manifest_edited_to_another_projector_is_refused(tmp_path):
    write_patterns(tmp_path, make_manifest("brute-force", (4, 4), 1), progress=False)
    d = json.loads((tmp_path / "manifest.json").read_text())
    d["projector"] = [4, 8]
    with pytest.raises(AcquisitionError, match="pattern list"):
        Manifest.from_dict(d, tmp_path / "manifest.json")


def test_a_manifest_is_read_as_the_canonical_one(tmp_path):
    """Numbers that equal bigT's but are not of its type (an index of 5.0, inverted: 1)
    pass the comparison; what comes back is bigT's own (an int index to index arrays)."""
    write_patterns(tmp_path, make_manifest("brute-force", (4, 4), 1, graycode=True),
                   progress=False)
    d = json.loads((tmp_path / "manifest.json").read_text())
    d["patterns"][5]["index"] = 3.0
    d["patterns"][-1]["inverted"] = 1
    m = Manifest.from_dict(d, tmp_path / "manifest.json")
    assert type(m.patterns[5].index) is int and m.patterns[-1].inverted is True
    assert m == make_manifest("brute-force", (4, 4), 1, graycode=True)


def test_too_many_patterns_are_refused_before_they_are_listed():
    from bigT.acquisition.manifest import MAX_PATTERNS, pattern_count

    assert pattern_count("brute-force", (2160, 3840), 1, graycode=True) <= MAX_PATTERNS
    with pytest.raises(AcquisitionError, match="needs 10000000002 patterns"):
        make_manifest("brute-force", (100000, 100000), 1)
    for method in ("brute-force", "stripes", "graycode"):
        for graycode in (False, True):
            m = make_manifest(method, (12, 20), 2, graycode=graycode)
            assert pattern_count(method, (12, 20), 2, graycode=graycode) == len(m.patterns)


@pytest.mark.parametrize("projector, s", [((6, 8), 4), ((6, 8), 7), ((5, 8), 2)])
def test_superpixels_must_divide_the_projector(projector, s):
    with pytest.raises(AcquisitionError, match="super-pixels"):
        make_manifest("brute-force", projector, s)
