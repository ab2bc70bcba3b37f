"""The calibrated acquisition (issue #29): the ramp, camera responses, exposure brackets
and the simulated nonlinear rig, grey and colour.

References are independent of the build: the rig's own projector curve
(NonlinearRig.project), the scene's T scaled as the simulation documents, and captures
written here by hand."""

import json

import numpy as np
import pytest

from bigT import scenes
from bigT.acquisition import build_transport, make_manifest, read_manifest, write_patterns
from bigT.acquisition import manifest as manifest_module
from bigT.acquisition.brackets import seconds_in_label
from bigT.acquisition.captures import Captures
from bigT.acquisition.ramp import PROJECTOR_RESPONSE_FILE, PROJECTOR_RESPONSE_KEY
from bigT.acquisition.simulate import read_camera_model, simulate_captures
from bigT.calibration import CameraResponse, NonlinearRig, load_projector_response
from bigT.cli import acquire_cmds, main
from bigT.errors import AcquisitionError
from bigT.images import write_image
from bigT.storage import open as open_store

GRID = (6, 8)
PROJECTOR, S = (12, 16), 2
CAMERA = (30, 40)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("calibrated")
    return scenes.corner(size=GRID, path=root / "scene.zarr", overwrite=True)


def _patterns(folder, channels=1, ramp=17):
    write_patterns(folder, make_manifest("brute-force", PROJECTOR, S, graycode=True,
                                         channels=channels, ramp_levels=ramp), progress=False)
    return folder


def _true_above_black(rig, v):
    b = np.asarray(rig.projector_black, dtype=np.float64)
    return (rig.project(v) - b) / (1 - b)


# --- manifest -------------------------------------------------------------------------

def test_the_ramp_is_listed_with_its_levels_and_primaries(tmp_path):
    m = read_manifest(_patterns(tmp_path / "p", channels=3, ramp=17))
    assert m.ramp_levels == 17
    ramp = m.ramp()
    assert len(ramp) == 3 * 17
    for j in "RGB":
        levels = [p.level for p in ramp if p.primary == j]
        assert levels[0] == 0.0 and levels[-1] == 1.0 and np.all(np.diff(levels) > 0)
        # exact 8-bit codes: what the PNG holds is the level recorded
        assert np.allclose(np.array(levels) * 255, np.rint(np.array(levels) * 255), atol=1e-9)
    d = json.loads((tmp_path / "p" / "manifest.json").read_text())
    assert d["ramp_levels"] == 17
    entry = next(e for e in d["patterns"] if e["file"] == "ramp_16_G.png")
    assert entry == {"file": "ramp_16_G.png", "kind": "ramp", "primary": "G", "level": 1.0}


def test_a_set_without_ramp_is_written_as_before(tmp_path):
    d = make_manifest("stripes", PROJECTOR, S).to_dict()
    assert "ramp_levels" not in d and all(p["kind"] != "ramp" for p in d["patterns"])


@pytest.mark.parametrize("levels", [5, 16, 257, True])
def test_ramp_levels_out_of_range_are_refused(levels):
    with pytest.raises(AcquisitionError, match="ramp_levels must be 0"):
        make_manifest("brute-force", PROJECTOR, S, ramp_levels=levels)


def test_the_cli_bounds_agree_with_the_library():
    assert (acquire_cmds.MIN_RAMP_LEVELS, acquire_cmds.MAX_RAMP_LEVELS,
            acquire_cmds.DEFAULT_RAMP_LEVELS) == (
        manifest_module.MIN_RAMP_LEVELS, manifest_module.MAX_RAMP_LEVELS,
        manifest_module.DEFAULT_RAMP_LEVELS)


# --- the ramp round trip ---------------------------------------------------------------

def test_grey_ramp_round_trip_on_the_nonlinear_rig(scene, tmp_path):
    """simulate nonlinear -> build: the fitted response against the rig's true curve
    (above black), within the library's documented bound for a 17-level ramp (PCHIP's
    interpolation error 2.8e-4, measured 3.6e-4 with 48x48-pixel means; ours average
    fewer pixels of a 16-bit camera: a few 1e-4)."""
    pat = _patterns(tmp_path / "p")
    rig = NonlinearRig(bits=16, camera=CameraResponse("gamma", gamma=2.2))
    simulate_captures(scene.path, pat, tmp_path / "c", camera=CAMERA, rig=rig, fmt="png16",
                      progress=False)
    report = build_transport(pat, tmp_path / "c", tmp_path / "T.zarr", progress=False,
                             camera_response="gamma:2.2")
    T = open_store(tmp_path / "T.zarr")
    assert T.metadata[PROJECTOR_RESPONSE_KEY] == PROJECTOR_RESPONSE_FILE
    fitted = load_projector_response(tmp_path / "T.zarr" / PROJECTOR_RESPONSE_FILE)
    assert fitted.channels == ("grey",)
    v = np.linspace(0, 1, 1001)
    error = np.abs(fitted.to_linear(v, above_black=True) - _true_above_black(rig, v)).max()
    assert error < 1e-3, error
    assert abs(fitted.black[0]) < 1e-3  # the black capture subtracted: black is 0
    assert report.projector_response is not None


def test_colour_ramp_per_channel(tmp_path):
    """Three primaries with their own gamma and black: each channel's fitted curve is
    its own primary's."""
    scene = scenes.corner(size=GRID, path=tmp_path / "grey.zarr", overwrite=True)
    colour = _colour_scene(scene, tmp_path / "colour.zarr")
    pat = _patterns(tmp_path / "p", channels=3)
    rig = NonlinearRig(projector_gamma=(1.8, 2.2, 2.6), projector_black=(0.01, 0.02, 0.04),
                       projector_shoulder=(0.1, 0.3, 0.2), bits=16)
    simulate_captures(colour, pat, tmp_path / "c", camera=CAMERA, rig=rig, fmt="png16",
                      progress=False)
    build_transport(pat, tmp_path / "c", tmp_path / "T.zarr", progress=False,
                    camera_response="gamma:2.2")
    fitted = load_projector_response(tmp_path / "T.zarr" / PROJECTOR_RESPONSE_FILE)
    assert fitted.channels == ("R", "G", "B")
    v = np.linspace(0, 1, 501)
    truth = _true_above_black(rig, np.repeat(v[:, None], 3, axis=1))
    errors = np.abs(fitted.to_linear(np.repeat(v[:, None], 3, axis=1), above_black=True)
                    - truth).max(axis=0)
    assert np.all(errors < 2e-3), errors
    # the channels differ by far more than the error: each is its own primary's
    assert np.abs(truth[:, 0] - truth[:, 2]).max() > 20 * errors.max()


def _colour_scene(grey, path):
    """A colour T with independent primaries (identity mixings): kron(T, I3)."""
    import scipy.sparse as sp

    import bigT

    T = grey.T.to_scipy()
    return bigT.from_scipy(sp.csr_array(sp.kron(T, np.eye(3))), path, image_shape=GRID,
                           channels=3, tile_size=24, pixel_order="tile-major",
                           image_tile=(2, 4)).path


def test_a_flat_ramp_is_refused_naming_the_captures(scene, tmp_path, capsys):
    pat = _patterns(tmp_path / "p")
    simulate_captures(scene.path, pat, tmp_path / "c", camera=CAMERA, progress=False)
    m = read_manifest(pat)
    dark = (tmp_path / "c" / "ramp_00.png")
    for p in m.ramp():  # every ramp frame as dark as the black one: projector off
        (tmp_path / "c" / f"{p.stem}.png").write_bytes(dark.read_bytes())
    status = main(["acquire", "build", str(pat), str(tmp_path / "c"), "-o",
                   str(tmp_path / "T.zarr"), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1
    assert str(tmp_path / "c") in err[0] and "projector ramp: ramp flat" in err[0]
    assert not (tmp_path / "T.zarr").exists()


def test_a_falling_ramp_is_refused(scene, tmp_path, capsys):
    pat = _patterns(tmp_path / "p")
    simulate_captures(scene.path, pat, tmp_path / "c", camera=CAMERA, progress=False)
    c = tmp_path / "c"
    # levels 8 and 12 swapped: the ramp falls between them
    a, b = (c / "ramp_08.png").read_bytes(), (c / "ramp_12.png").read_bytes()
    (c / "ramp_08.png").write_bytes(b)
    (c / "ramp_12.png").write_bytes(a)
    status = main(["acquire", "build", str(pat), str(c), "-o", str(tmp_path / "T.zarr"),
                   "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1 and "ramp not monotone in channel grey" in err[0]


# --- brackets -------------------------------------------------------------------------

@pytest.mark.parametrize("label, seconds", [
    ("0.004", 0.004), ("1e-3", 1e-3), ("2.5", 2.5), ("1-250", 1 / 250), ("1-250s", 1 / 250),
    (".5", 0.5), ("8", 8.0), ("a", None), ("e1", None), ("0", None), ("1-0", None)])
def test_exposure_labels(label, seconds):
    assert seconds_in_label(label) == seconds


def _tiny_set(folder):
    """A 1x1-super-pixel brute-force set of a 2x2 projector, no Gray code: 6 patterns."""
    m = make_manifest("brute-force", (2, 2), 1)
    write_patterns(folder, m, progress=False)
    return m


def _write_bracket(folder, m, times, *, skip=None, label=None, codes=None):
    """Every pattern at every time, 8-bit: a uniform image whose code grows with t."""
    folder.mkdir(parents=True, exist_ok=True)
    for k, p in enumerate(m.patterns):
        for i, t in enumerate(times):
            if skip == (p.stem, t):
                continue
            name = f"{p.stem}@{label(i) if label else format(t, 'g')}.png"
            value = codes(p, t) if codes else min(0.05 + 0.1 * k * t, 0.9)
            write_image(folder / name, np.full((4, 5), value), bits=8)


def test_brackets_are_parsed_in_rising_order(tmp_path):
    m = _tiny_set(tmp_path / "p")
    _write_bracket(tmp_path / "c", m, (0.01, 0.1, 1.0))
    cap = Captures(m, tmp_path / "c")
    assert cap.bracketed and cap.exposures == (0.01, 0.1, 1.0)
    assert [p.name for p in cap.brackets["white"].paths] == ["white@0.01.png", "white@0.1.png",
                                                            "white@1.png"]


def _fails(tmp_path, m, match):
    with pytest.raises(AcquisitionError, match=match) as info:
        Captures(m, tmp_path / "c")
    assert "\n" not in str(info.value) and str(tmp_path / "c") in str(info.value)
    return str(info.value)


def test_a_missing_exposure_names_the_pattern(tmp_path):
    m = _tiny_set(tmp_path / "p")
    _write_bracket(tmp_path / "c", m, (0.01, 0.1, 1.0), skip=("sp_2", 0.1))
    _fails(tmp_path, m, r"bracket of pattern 'sp_2': no capture at 1/10 s.*missing")


def test_exposures_out_of_order_name_the_pattern(tmp_path):
    """Labels without times, EXIF absent: the time is missing; with the time in the
    label the order is the times'. Out of order: labels whose times fall."""
    m = _tiny_set(tmp_path / "p")
    _write_bracket(tmp_path / "c", m, (0.01, 0.1), label=lambda i: ("a", "b")[i])
    _fails(tmp_path, m, r"bracket of pattern 'black': black@a.png has no exposure time")


def test_exposures_out_of_order_by_exif(tmp_path, monkeypatch):
    from bigT.acquisition import brackets

    m = _tiny_set(tmp_path / "p")
    _write_bracket(tmp_path / "c", m, (0.01, 0.1), label=lambda i: ("e1", "e2")[i])
    exif = {"e1": 0.1, "e2": 0.01}  # the camera's times fall as the labels rise
    monkeypatch.setattr(brackets, "_exif_seconds",
                        lambda path: exif[path.stem.partition("@")[2]])
    _fails(tmp_path, m, r"bracket of pattern 'black': exposures out of order: 1/100 s "
                        r"\(black@e2.png\) after 1/10 s")


def test_a_name_disagreeing_with_its_exif_is_refused(tmp_path, monkeypatch):
    from bigT.acquisition import brackets

    m = _tiny_set(tmp_path / "p")
    _write_bracket(tmp_path / "c", m, (0.01, 0.1))
    monkeypatch.setattr(brackets, "_exif_seconds", lambda path: 0.004)
    _fails(tmp_path, m, r"black@0.01.png says 1/100 s but its EXIF 1/250 s")


def test_a_single_capture_among_brackets_is_refused(tmp_path):
    m = _tiny_set(tmp_path / "p")
    _write_bracket(tmp_path / "c", m, (0.01, 0.1))
    write_image(tmp_path / "c" / "sp_1.png", np.full((4, 5), 0.3), bits=8)
    _fails(tmp_path, m, r"bracket of pattern 'sp_1': sp_1.png has no exposure time while "
                        "other captures are brackets")


def test_all_saturated_names_the_pattern(tmp_path):
    m = _tiny_set(tmp_path / "p")
    _write_bracket(tmp_path / "c", m, (0.01, 0.1),
                   codes=lambda p, t: 1.0 if p.stem == "white" else 0.3)
    cap = Captures(m, tmp_path / "c")
    with pytest.raises(AcquisitionError, match=r"bracket of pattern 'white': 20 pixels "
                                               r"saturated in every exposure"):
        cap.linear(m.single("white"))


def test_a_bracket_merges_to_the_radiance(tmp_path):
    """Linear 16-bit captures of radiance E at t: E t; the merge gives E back."""
    m = _tiny_set(tmp_path / "p")
    radiance = {p.stem: 0.2 + 0.1 * k for k, p in enumerate(m.patterns)}
    _write_bracket(tmp_path / "c", m, (0.5, 1.0, 2.0),
                   codes=lambda p, t: min(radiance[p.stem] * t, 1.0))
    cap = Captures(m, tmp_path / "c")
    for p in m.patterns:
        assert np.allclose(cap.linear(p), radiance[p.stem], atol=2 / 255)


# --- camera responses -----------------------------------------------------------------

@pytest.mark.parametrize("spec, undo", [
    ("linear", lambda z: z),
    ("srgb", lambda z: np.where(z <= 0.04045, z / 12.92, ((z + 0.055) / 1.055) ** 2.4)),
    ("gamma:2.2", lambda z: z ** 2.2)])
def test_camera_responses_apply_to_single_exposures(tmp_path, spec, undo):
    m = _tiny_set(tmp_path / "p")
    (tmp_path / "c").mkdir()
    for k, p in enumerate(m.patterns):
        write_image(tmp_path / "c" / f"{p.stem}.png", np.full((4, 5), 0.1 + 0.15 * k), bits=16)
    cap = Captures(m, tmp_path / "c", camera_response=spec)
    for k, p in enumerate(m.patterns):
        z = np.rint((0.1 + 0.15 * k) * 65535) / 65535
        assert np.allclose(cap.linear(p), undo(z), rtol=0, atol=1e-12)


def test_a_table_camera_response(tmp_path):
    m = _tiny_set(tmp_path / "p")
    (tmp_path / "c").mkdir()
    for p in m.patterns:
        write_image(tmp_path / "c" / f"{p.stem}.png", np.full((4, 5), 128 / 255), bits=8)
    table = np.linspace(0, 1, 256) ** 3
    np.save(tmp_path / "curve.npy", table)
    cap = Captures(m, tmp_path / "c", camera_response=str(tmp_path / "curve.npy"))
    assert np.allclose(cap.linear(m.single("white")), table[128])


def test_gamma_and_camera_response_together_are_refused(tmp_path):
    m = _tiny_set(tmp_path / "p")
    _write_bracket(tmp_path / "c", m, (1.0,))
    with pytest.raises(AcquisitionError, match="give the camera's response once"):
        Captures(m, tmp_path / "c", gamma=2.2, camera_response="srgb")


def test_recover_needs_brackets(tmp_path):
    m = _tiny_set(tmp_path / "p")
    (tmp_path / "c").mkdir()
    for p in m.patterns:
        write_image(tmp_path / "c" / f"{p.stem}.png", np.full((4, 5), 0.5), bits=8)
    with pytest.raises(AcquisitionError, match="recover needs exposure brackets"):
        Captures(m, tmp_path / "c", camera_response="recover")


# --- the whole loop on the command line -------------------------------------------------

def _T_error(scene, captures, store):
    """Relative error of the built T against the scene's truth, as the simulation
    documents it: expected_scale * T * (1 - b); diagonal and off-diagonal parts."""
    model = read_camera_model(captures)
    rig = json.loads((captures / "simulation.json").read_text())["rig"]
    scale = model.expected_scale(scene.pixel_order) * (1 - rig["projector_black"])
    truth = scene.T.to_scipy(output_order="matrix").toarray() * scale[:, None]
    built = open_store(store).to_scipy(output_order="matrix").toarray()
    off = ~np.eye(len(truth), dtype=bool)
    return (np.linalg.norm(np.diag(built) - np.diag(truth)) / np.linalg.norm(np.diag(truth)),
            np.linalg.norm((built - truth)[off]) / np.linalg.norm(truth[off]))


def test_simulate_brackets_then_build_on_the_command_line(scene, tmp_path, capsys):
    """The nonlinear rig's loop: one 8-bit exposure, then a bracket of three; the bracket
    measures the interreflection (off-diagonal) far better, the direct light as well."""
    pat = tmp_path / "p"
    assert main(["acquire", "patterns", "--method", "brute-force", "--projector", "12x16",
                 "--superpixel", "2", "--graycode", "-o", str(pat), "--no-progress"]) == 0
    assert "a ramp of 17 levels" in capsys.readouterr().out
    errors = {}
    for name, extra in (("one", []), ("three", ["--exposures", "1,8,64"])):
        cap = tmp_path / name
        assert main(["acquire", "simulate", str(scene.path), str(pat), "-o", str(cap),
                     "--camera", "30x40", "--projector-gamma", "2.2", *extra,
                     "--no-progress"]) == 0
        out = capsys.readouterr().out
        assert "nonlinear rig" in out
        assert main(["acquire", "build", str(pat), str(cap), "-o", str(tmp_path / f"{name}.zarr"),
                     "--camera-response", "gamma:2.2", "--no-progress"]) == 0
        out = capsys.readouterr().out
        assert "camera response: gamma 2.2" in out and "projector response: fitted" in out
        assert (tmp_path / f"{name}-projector-response.png").is_file()
        errors[name] = _T_error(scene, cap, tmp_path / f"{name}.zarr")
    assert sorted(p.name for p in (tmp_path / "three").glob("white*")) == [
        "white@1.png", "white@64.png", "white@8.png"]
    assert errors["three"][1] < 0.5 * errors["one"][1], errors
    assert errors["three"][0] < 0.02 and errors["one"][0] < 0.02, errors


def test_simulate_refuses_the_linear_cameras_options_with_the_rig(scene, tmp_path, capsys):
    pat = _patterns(tmp_path / "p")
    status = main(["acquire", "simulate", str(scene.path), str(pat), "-o", str(tmp_path / "c"),
                   "--camera", "30x40", "--bits", "16", "--noise", "0.01", "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1 and "linear camera's" in err[0]
