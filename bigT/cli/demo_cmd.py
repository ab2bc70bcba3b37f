"""``bigT demo``: the main job on an embedded default, end to end, with a report.

A synthetic concave wall corner (``bigT scene corner``), its stratified inverse
(``bigT invert``), the error of that inverse against the scene's exact inverse
F^-1 (I - A), the compensation of a built-in test pattern and of a constant image
(``bigT compensate --simulate``), and the bounce separation of a white image
(``bigT bounces``). Every step is the real sub-command; what each prints is collected in
``report.md`` in the demo folder beside the PNGs it refers to.
"""

from __future__ import annotations

import contextlib
import io
import shutil
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from ..atomic import atomic_output
from ..errors import BigTError
from ._argtypes import image_size, integer, number
from ._options import add_progress

# The library's layers are imported inside each command's functions, where the
# command runs: building the parser imports every command module, and a command
# should pay only for the layers it uses (stores: zarr ~0.3 s; compensation ~0.5 s).
# Even numpy (~0.1 s) is imported where the demo runs: `bigT --help` does not need it.
if TYPE_CHECKING:
    import numpy as np

#: Defaults of the demo: a scene that builds, inverts and compensates in about a minute
#: on a 2-core machine.
DEMO_SIZE = (192, 256)
DEMO_FF_CUT = 3e-4
DEMO_THRESHOLD = 1e-6
DEMO_TERMS = 4
#: Grey level of the constant target: low enough that the compensated projector input
#: stays below 1 where the corner receives the least light.
DEMO_CONSTANT = 0.4
#: The colour part: an RGB Cornell box (red and green walls bleed colour onto the white
#: ones) small enough to add a few seconds; its inverse takes the global-mixing path.
DEMO_COLOUR_SIZE = (48, 64)
#: Its form-factor cut and threshold: ~50 entries per row of T (a Cornell box's patches
#: all see each other; at the grey demo's cut T would be nearly dense, and its inverse
#: take minutes instead of seconds).
DEMO_COLOUR_FF_CUT = 1e-2
DEMO_COLOUR_THRESHOLD = 1e-5
#: The colour target is the test pattern as the surfaces would show it lit directly (F l,
#: F the per-pixel 3x3 first bounce): in every pixel's gamut, so compensation cancels
#: the colour mixing and the bleeding, not clipping. The pattern's range:
DEMO_COLOUR_RANGE = (0.2, 0.8)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="build, invert and compensate a synthetic corner scene, with a report",
        description="Run the main job on an embedded default: a synthetic wall-corner "
                    "scene, its stratified inverse, the compensation of a test pattern and "
                    "a constant image, bounce separation, and a report (report.md + PNGs).")
    p.add_argument("--dir", default="bigT-demo", help="output folder (default %(default)s; "
                   "its previous demo outputs are replaced)")
    p.add_argument("--size", type=image_size, default=f"{DEMO_SIZE[0]}x{DEMO_SIZE[1]}",
                   metavar="HxW",
                   help="projector size of the synthetic corner scene (default %(default)s)")
    p.add_argument("--terms", type=integer(0), default=DEMO_TERMS,
                   help="series terms n of the inverse T_n^-1 (default %(default)s)")
    p.add_argument("--prune", type=number(0), default=None,
                   help="prune threshold of the inverse (default: bigT invert's)")
    add_progress(p)
    p.set_defaults(func=demo_cmd)


def test_pattern(shape, lo: float = 0.08, hi: float = 0.42) -> np.ndarray:
    """A grey test image of ``shape`` (H, W) in [lo, hi]: a horizontal ramp, a ring and
    vertical bars, so errors show in smooth and sharp regions alike."""
    import numpy as np

    H, W = shape
    y, x = np.mgrid[0:H, 0:W]
    ramp = x / max(W - 1, 1)
    r = np.hypot((y - H / 2) / H, (x - W / 2) / W)
    ring = ((r > 0.18) & (r < 0.26)).astype(float)
    bars = ((x // max(W // 16, 1)) % 2 == 0) & (y > 0.72 * H)
    img = 0.45 * ramp + 0.55 * np.maximum(ring, bars)
    return lo + (hi - lo) * img


def colour_test_pattern(shape, lo: float = 0.06, hi: float = 0.36) -> np.ndarray:
    """An RGB test image (H, W, 3) of linear light in [lo, hi]: a hue ramp across,
    darkening downwards, with a grey ring, so colour and grey errors both show."""
    import numpy as np

    H, W = shape
    y, x = np.mgrid[0:H, 0:W] / np.array([max(H - 1, 1), max(W - 1, 1)])[:, None, None]
    hue = 2 * np.pi * x
    rgb = np.stack([0.5 + 0.5 * np.cos(hue - k * 2 * np.pi / 3) for k in range(3)], -1)
    ring = (np.abs(np.hypot(y - 0.5, x - 0.5) - 0.22) < 0.04)[..., None]
    img = np.where(ring, 0.9, 0.35 + 0.6 * rgb * (0.3 + 0.7 * y[..., None]))
    return lo + (hi - lo) * img


def direct_view(F: np.ndarray, light: np.ndarray) -> np.ndarray:
    """What the camera sees of projector image ``light`` (H, W, 3) by direct light only:
    each pixel's 3x3 first bounce F (H W, 3, 3) applied to its RGB."""
    import numpy as np

    H, W, _ = light.shape
    return np.einsum("pij,pj->pi", F, light.reshape(-1, 3)).reshape(H, W, 3)


class _Tee(io.TextIOBase):
    def __init__(self, *streams):
        self.streams = streams

    def write(self, s):
        for st in self.streams:
            st.write(s)
        return len(s)

    def flush(self):
        for st in self.streams:
            st.flush()


class _StepFailed(Exception):
    """A demo step's command failed; it has printed its one-line error already, so the
    demo stops with its status and adds no second line."""

    def __init__(self, status: int):
        super().__init__(status)
        self.status = status


def _step(title: str, argv: list[str], log: list) -> None:
    """Run ``bigT <argv>`` in this process, echoing and recording what it prints.

    Raises
    ------
    _StepFailed
        With the command's exit status when it is not 0.
    """
    from . import main

    print(f"\n== {title}\n$ bigT {' '.join(argv)}", flush=True)
    buf = io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(_Tee(sys.stdout, buf)):
        status = main(argv)
    if status:
        raise _StepFailed(status)
    log.append((title, "bigT " + " ".join(argv), buf.getvalue(), time.perf_counter() - t0))


#: What a demo writes in its folder; a rerun replaces exactly these.
DEMO_OUTPUTS = ("T.zarr", "X.zarr", "inputs", "compensated", "bounces", "report.md",
                "T-preview.png", "invert.json", "colour")
#: Written first into the demo folder, so that a rerun (even after an interrupted demo)
#: knows the folder is the demo's.
DEMO_MARKER = ".bigT-demo"


def _clear_previous_demo(out: Path) -> None:
    """Remove an earlier demo's outputs from ``out`` and mark it as the demo's folder.

    Refuses a non-empty folder without the demo's marker, and one holding anything
    the demo does not write, so no user file is ever deleted."""

    if out.exists() and not out.is_dir():
        raise BigTError("is not a folder", out)
    entries = {p.name for p in out.iterdir()} if out.exists() else set()
    if entries and DEMO_MARKER not in entries:
        raise BigTError(f"is not empty and is not an earlier demo's folder (no {DEMO_MARKER}); "
                        "choose an empty or new folder with --dir", out)
    foreign = sorted(entries - set(DEMO_OUTPUTS) - {DEMO_MARKER})
    if foreign:
        raise BigTError("holds files the demo did not write (" + ", ".join(foreign[:3])
                        + "); choose another folder with --dir", out)
    for name in DEMO_OUTPUTS:
        p = out / name
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()
    out.mkdir(parents=True, exist_ok=True)
    (out / DEMO_MARKER).write_text("written by bigT demo; a rerun replaces this folder's "
                                   "demo outputs\n")


def demo_cmd(args) -> int:
    try:
        return _run_demo(args)
    except _StepFailed as exc:
        return exc.status


def _run_demo(args) -> int:
    import numpy as np

    from ..images import write_image
    from ..scenes import load
    from ..storage import open as open_store

    H, W = args.size
    out = Path(args.dir)
    _clear_previous_demo(out)
    quiet = [] if args.progress else ["--no-progress"]
    log: list = []
    t_start = time.perf_counter()

    T_path, X_path = out / "T.zarr", out / "X.zarr"
    _step("scene: a concave wall corner", [
        "scene", "corner", "--size", f"{H}x{W}", "-o", str(T_path), "--ff-cut", f"{DEMO_FF_CUT:g}",
        "--threshold", f"{DEMO_THRESHOLD:g}", "--overwrite"] + quiet, log)
    invert = ["invert", str(T_path), "-o", str(X_path), "--terms", str(args.terms),
              "--json", str(out / "invert.json")] + quiet
    if args.prune is not None:
        invert += ["--prune", f"{args.prune:g}"]
    _step(f"inverse: {args.terms} terms of the stratified inverse (power form)", invert, log)

    scene = load(T_path)
    X = open_store(X_path)
    err = scene.inverse_error(X)
    err0 = scene.inverse_error(1.0 / scene.T.diagonal().astype(np.float64))
    line = (f"error of X against the exact inverse F^-1 (I - A): {err:.3e} (relative "
            f"Frobenius; F^-1 alone: {err0:.3e})")
    print(f"\n== {line}")
    log.append(("error against the ground truth", "scene.inverse_error(X)", line + "\n", 0.0))

    inputs = out / "inputs"
    inputs.mkdir()
    write_image(inputs / "test_pattern.png", test_pattern((H, W)), bits=16)
    write_image(inputs / "constant.png", np.full((H, W), DEMO_CONSTANT), bits=16)
    write_image(inputs / "white.png", np.ones((H, W)), bits=16)
    comp = out / "compensated"
    comp.mkdir()
    for name in ("test_pattern", "constant"):
        _step(f"compensation of the {name.replace('_', ' ')}", [
            "compensate", str(X_path), str(inputs / f"{name}.png"), "-o",
            str(comp / f"{name}.png"), "--simulate", str(T_path), "--path", "explicit"] + quiet,
            log)
    _step("bounce separation of a white image", [
        "bounces", str(T_path), str(X_path), str(inputs / "white.png"), "--bounces", "3",
        "-o", str(out / "bounces"), "--format", "tif"] + quiet, log)

    colour_figures = _colour_part(out / "colour", quiet, log)

    total = time.perf_counter() - t_start
    report = _write_report(out, scene, log, total, colour_figures)
    print(f"\n== demo finished in {total:.1f} s; report -> {report}")
    return 0


def _colour_part(out: Path, quiet: list, log: list) -> list:
    """The colour Cornell box: its scene, the per-pixel 3x3 inverse (term 0, the classic
    colour method) and 4 terms, a colour test pattern compensated by each with the
    camera's view simulated; the views and their CIEDE2000 maps drawn in one figure.
    Returns the report's (caption, path) figures."""
    from ..metrics import delta_e_map, image_metrics
    from ..figures import colour_views
    from ..images import read_image, write_image
    from ..scenes import load

    H, W = DEMO_COLOUR_SIZE
    out.mkdir()
    T_path = out / "T.zarr"
    _step("colour: an RGB Cornell box (red and green walls)", [
        "scene", "cornell", "--colour", "--size", f"{H}x{W}", "-o", str(T_path),
        "--ff-cut", f"{DEMO_COLOUR_FF_CUT:g}", "--threshold", f"{DEMO_COLOUR_THRESHOLD:g}",
        "--overwrite"] + quiet, log)
    scene = load(T_path)
    pattern = colour_test_pattern((H, W), *DEMO_COLOUR_RANGE)
    desired = direct_view(scene.F, pattern)
    write_image(out / "test_pattern.png", desired, bits=16)  # 16-bit: linear light
    views = {"desired": desired}
    views["uncompensated"] = scene.T.matmul(desired.ravel()).reshape(desired.shape)
    for terms, label in ((0, "per-pixel 3x3 (term 0)"), (DEMO_TERMS, f"{DEMO_TERMS} terms")):
        X = out / f"X{terms}.zarr"
        _step(f"colour: inverse, {label}", ["invert", str(T_path), "-o", str(X), "--terms",
                                            str(terms)] + quiet, log)
        _step(f"colour: compensation with {label}", [
            "compensate", str(X), str(out / "test_pattern.png"), "-o",
            str(out / f"projector{terms}.png"), "--simulate", str(T_path)] + quiet, log)
        views[label] = read_image(out / f"projector{terms}_seen.png", channels=3)
    maps = {k: delta_e_map(v, desired) for k, v in views.items() if k != "desired"}
    lines = [f"{k}: {image_metrics(v, desired).describe()}" for k, v in views.items()
             if k != "desired"]
    log.append(("colour: what the camera sees against the desired image",
                "bigT.metrics.image_metrics", "\n".join(lines) + "\n", 0.0))
    figure = colour_views(out / "views.png", views, maps,
                          suptitle="colour Cornell box: the camera's view of a test pattern "
                                   "(top) and its CIEDE2000 difference from the desired image")
    return [("colour Cornell box: the camera's view of a white projector image", scene.preview),
            ("colour: desired | uncompensated | per-pixel 3x3 only | 4 terms, with dE2000 "
             "maps", figure)]


def _write_report(out: Path, scene, log, total: float, more_figures=()) -> Path:
    figures = [
        ("the scene: T 1 and scan lines", scene.preview),
        ("test pattern: desired | seen without | projector input | seen with compensation",
         out / "compensated" / "test_pattern_compare.png"),
        ("constant target", out / "compensated" / "constant_compare.png"),
        ("constant target, centre scan line (paper Fig. 10)",
         out / "compensated" / "constant_scanline.png"),
        ("bounce separation of a white image", out / "bounces" / "bounces.png"),
        *more_figures,
    ]
    lines = ["# bigT demo report", "",
             f"Finished in {total:.1f} s. Each step below but the error line is a `bigT` "
             "command, its output quoted as printed; the error line is computed by "
             "`bigT.scenes.Scene.inverse_error`.", ""]
    for title, cmd, text, seconds in log:
        lines += [f"## {title}", "", f"`{cmd}`" + (f" ({seconds:.1f} s)" if seconds else ""),
                  "", "```", text.rstrip(), "```", ""]
    lines += ["## Figures", ""]
    for caption, path in figures:
        if path is not None and Path(path).exists():
            rel = Path(path).resolve().relative_to(out.resolve())
            lines += [f"**{caption}**", "", f"![{caption}]({rel.as_posix()})", ""]
    report = out / "report.md"
    with atomic_output(report, "the demo report") as tmp:
        tmp.write_text("\n".join(lines))
    return report
