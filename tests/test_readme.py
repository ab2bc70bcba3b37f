"""The README runs as written: every line of its command-line tour, in order, in an
empty directory, and its Python example (twice: a second run must work too), with the
environment the README's commands set up (this interpreter's bin directory on PATH)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parent.parent / "README.md"


def _block(section: str, lang: str) -> str:
    """The first fenced block of ``lang`` after the heading ``section``."""
    text = README.read_text(encoding="utf-8")
    start = text.index(f"## {section}\n")
    m = re.compile(rf"```{lang}\n(.*?)```", re.S).search(text, start)
    assert m, f"no ```{lang} block under '## {section}'"
    return m.group(1)


def _env() -> dict:
    env = dict(os.environ)
    env["PATH"] = str(Path(sys.executable).parent) + os.pathsep + env.get("PATH", "")
    return env


def _run(cmd, cwd, **kw):
    proc = subprocess.run(cmd, cwd=cwd, env=_env(), capture_output=True, text=True,
                          timeout=600, **kw)
    assert proc.returncode == 0, f"{cmd}\n--- stdout\n{proc.stdout}\n--- stderr\n{proc.stderr}"
    return proc


def test_the_tour_runs_line_by_line(tmp_path):
    lines = [line for line in _block("A tour of the command line", "sh").splitlines()
             if line.strip() and not line.lstrip().startswith("#")]
    assert len(lines) >= 8
    for line in lines:
        _run(["bash", "-c", line], tmp_path)
    for made in ("T.zarr", "X.zarr", "projector.png", "seen.png", "bounces", "T.npz",
                 "T2.zarr"):
        assert (tmp_path / made).exists(), made
    import bigT

    a = bigT.open(tmp_path / "T.zarr").to_scipy(output_order="row-major")
    b = bigT.open(tmp_path / "T2.zarr").to_scipy(output_order="row-major")
    assert abs(a - b).max() == 0  # export and convert round-trip T


def test_the_python_example_runs_and_runs_again(tmp_path):
    code = _block("From Python", "python")
    for _ in range(2):
        out = _run([sys.executable, "-c", code], tmp_path).stdout.strip().splitlines()
        error = float(out[-1])  # the compensated error printed last
        assert 0 <= error < 1e-2  # 0.32 uncompensated


def test_the_acquisition_walkthrough_runs_line_by_line(tmp_path):
    lines = [line for line in _block("Measuring T with a projector and a camera", "sh")
             .splitlines() if line.strip() and not line.lstrip().startswith("#")]
    assert len(lines) == 5
    for line in lines:
        _run(["bash", "-c", line], tmp_path)
    for made in ("T.zarr", "T-correspondence.png", "T-validation.png", "X.zarr"):
        assert (tmp_path / made).exists(), made


def test_the_colour_section_runs_line_by_line(tmp_path):
    lines = [line for line in _block("Colour", "sh").splitlines()
             if line.strip() and not line.lstrip().startswith("#")]
    assert len(lines) == 4
    outputs = [_run(["bash", "-c", line], tmp_path).stdout for line in lines]
    assert "colour path: global colour mixing" in outputs[1]  # the scene records its rig
    import bigT

    a = bigT.open(tmp_path / "C.zarr").to_scipy(output_order="row-major")
    b = bigT.open(tmp_path / "C2.zarr").to_scipy(output_order="row-major")
    assert bigT.open(tmp_path / "C2.zarr").channels == 3 and abs(a - b).max() == 0


def test_the_calibration_example_runs_line_by_line(tmp_path):
    """The nonlinear simulated rig end to end: scene, patterns with a ramp, brackets,
    build with the camera's response, invert, and compensate at the camera's resolution
    into the projector's own, through the response T's store keeps."""
    lines = [line for line in _block("Calibrating a rig", "sh").splitlines()
             if line.strip() and not line.lstrip().startswith("#")]
    assert len(lines) == 7
    outputs = [_run(["bash", "-c", line], tmp_path).stdout for line in lines]
    assert "the floor dropped" in outputs[3] or "kept all the interreflected" in outputs[3]
    assert "projector_response.json, stored with T" in outputs[-1]  # found through X
    assert "camera image 40x52 -> 12x16 super-pixels -> projector 24x32" in outputs[-1]
    import imageio.v3 as iio

    projector = iio.imread(tmp_path / "rig-projector.png")
    assert projector.shape == (24, 32) and projector.dtype == np.uint8
    assert (tmp_path / "rig-projector_seen.png").exists()
