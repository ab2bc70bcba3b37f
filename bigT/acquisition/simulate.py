"""A camera without a rig: ``bigT acquire simulate`` (:func:`simulate_captures`).

Renders, from a synthetic scene's T (or any transport store with an image shape), the
image a camera of another resolution would capture for each pattern:

* the camera frames the projected area with a margin (:data:`MARGIN` of each side sees
  no projector light) and a smooth warp (lens and perspective), so each projector
  super-pixel is seen by a patch of camera pixels of uneven size and shape;
* a smooth, uneven gain over the frame (vignetting and surface orientation);
* an exposure that puts the brightest pixel of the white pattern at :data:`PEAK`;
* additive Gaussian noise, a black level, and optionally a gamma (stored = linear^(1/g)),
  then the file format's quantisation (16-bit PNG by default).

A colour T (3 n x 3 n, index 3 p + c) with a colour pattern set renders RGB captures:
the pattern images (H, W, 3), averaged over super-pixels, are T's input in matrix order,
T l the camera super-pixels' R, G, B, each channel with its own noise (``noise`` one
value or three). The rig's colour mixing is T's own (a colour scene's rig model), so the
camera here adds no mixing of its own: gain and exposure are the same for its channels.

The camera's model is written beside the captures as ``simulation.json`` (a file bigT
acquire build ignores), so the T a build recovers can be compared with
``exposure * diag(mean gain of each group) * T_scene`` (:meth:`CameraModel.expected_scale`).

The nonlinear rig (``rig``, a :class:`bigT.calibration.NonlinearRig`) replaces the
linear projector and camera: each pattern's values v go through the projector's
response r(v) (a gamma over a black level, under a soft shoulder: black is r(0) > 0
everywhere a pattern is dark), the scene's light is captured at each of ``exposures``
seconds with shot and read noise, clipped at the full well, through the camera's
response and quantised to its bits (PNG). One exposure writes ``<pattern>.png``, several
the bracket layout ``<pattern>@<seconds>.png`` (:mod:`.brackets`). The radiance is
scaled so that the white pattern's brightest pixel fills :data:`PEAK` of the full well
in the *shortest* exposure; the longer ones saturate the direct light and lift the
faint interreflection out of the quantisation. A build of these captures recovers
``expected_scale * T_scene * (1 - b)`` (the black capture, b, subtracted; of a colour
T, primary j's column scaled by its own 1 - b_j). ``simulation.json`` records the rig
(``rig``) and the exposures.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..atomic import atomic_output
from ..calibration import NonlinearRig
from ..errors import UNSET, AcquisitionError, Option
from ..images import read_image, write_image
from ..progress import progress_bar
from ..storage import PixelOrder
from ..storage import open as open_store
from .correspondence import Correspondence
from .formats import FORMATS
from .manifest import Manifest, patterns_folder, read_manifest

MARGIN = 0.05
PEAK = 0.9
WARP = 0.12  # amplitude of the warp, in super-pixels
SIMULATION = "simulation.json"
BATCH = 64


@dataclass(frozen=True)
class CameraModel:
    """Where each camera pixel looks, and with which gain.

    Attributes
    ----------
    camera : (int, int), (Hc, Wc)
    grid : (int, int), the projector's super-pixel grid
    exposure : float, multiplies every capture's light
    noise : float, or (float, float, float) for R, G, B: the noise std of a pixel
    black, gamma : float
    """

    camera: tuple[int, int]
    grid: tuple[int, int]
    exposure: float = 1.0
    noise: float | tuple[float, ...] = 0.0
    black: float = 0.0
    gamma: float = 1.0

    def superpixel_of(self) -> np.ndarray:
        """ndarray (Hc, Wc) int64: row-major grid index each pixel sees, -1 outside."""
        hc, wc = self.camera
        gh, gw = self.grid
        y, x = np.meshgrid((np.arange(hc) + 0.5) / hc, (np.arange(wc) + 0.5) / wc, indexing="ij")
        # frame coordinates in [0, 1] -> projected area with a margin, warped smoothly
        u = (y - MARGIN) / (1 - 2 * MARGIN) * gh + WARP * np.sin(2 * np.pi * x) * np.sin(np.pi * y)
        v = (x - MARGIN) / (1 - 2 * MARGIN) * gw + WARP * np.sin(2 * np.pi * y) * np.cos(np.pi * x)
        inside = (u >= 0) & (u < gh) & (v >= 0) & (v < gw)
        r = np.clip(np.floor(u), 0, gh - 1).astype(np.int64)
        c = np.clip(np.floor(v), 0, gw - 1).astype(np.int64)
        return np.where(inside, r * gw + c, -1)

    def gain(self) -> np.ndarray:
        """ndarray (Hc, Wc), about 0.57 to 1.05: vignetting times a gentle tilt."""
        hc, wc = self.camera
        y, x = np.meshgrid(np.linspace(-1, 1, hc), np.linspace(-1, 1, wc), indexing="ij")
        return (1 - 0.125 * (x ** 2 + y ** 2)) * (0.9 + 0.1 * x) * (0.95 + 0.05 * y)

    def expected_scale(self, order: PixelOrder) -> np.ndarray:
        """(n,) float64, matrix order: exposure x mean gain of each super-pixel's camera
        pixels (0 for super-pixels no pixel sees) -- the row scale a noise-free build
        recovers T_scene with (of a colour T, the same for a pixel's three rows)."""
        # the same group means a build takes, over the true correspondence
        groups = Correspondence(self.superpixel_of(), self.grid, "simulation").reducer(order)
        gain = self.gain()
        if order.channels > 1:
            gain = np.repeat(gain[:, :, None], order.channels, axis=2)
        return self.exposure * groups(gain)

    def render(self, light: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Camera images of scene light.

        Parameters
        ----------
        light : ndarray, shape (K, gh, gw), or (K, gh, gw, 3) for colour: T l of K
            patterns as grid images

        Returns
        -------
        ndarray, shape (K, Hc, Wc) or (K, Hc, Wc, 3), float64, stored values
        (gamma-encoded, unclipped)
        """
        sp = self.superpixel_of()
        K, channels = len(light), light.shape[3] if light.ndim == 4 else 1
        seen = light.reshape(K, -1, channels)[:, np.maximum(sp, 0)]  # (K, Hc, Wc, channels)
        seen = np.where((sp >= 0)[None, :, :, None], seen, 0.0)
        linear = self.exposure * self.gain()[:, :, None] * seen + self.black
        if light.ndim == 3:
            linear = linear[..., 0]
        if np.any(self.noise):
            # one std for all channels, or one for each (R, G, B: the last axis)
            linear = linear + rng.normal(0.0, 1.0, size=linear.shape) * np.asarray(self.noise)
        if self.gamma != 1.0:
            linear = np.power(np.maximum(linear, 0.0), 1.0 / self.gamma)
        return linear


def _pattern_vectors(manifest: Manifest, folder: Path, patterns, order: PixelOrder,
                     light=None) -> np.ndarray:
    """The projector's light for ``patterns`` (``light(values)``, the identity for a
    linear projector), averaged over super-pixels, in matrix order: (n, K)."""
    s = manifest.superpixel
    gh, gw = manifest.grid
    light = light or (lambda values: values)
    images = np.stack([light(_pattern_file(folder / p.file, manifest))
                       .reshape(gh, s, gw, s, -1).mean(axis=(1, 3)) for p in patterns])
    return order.to_matrix(images if manifest.channels > 1 else images[..., 0])


def _pattern_file(path: Path, manifest: Manifest) -> np.ndarray:
    """A pattern image as written: (H, W) grey, (H, W, 3) colour; refused (naming it)
    when it is not the projector's size or the set's channels."""
    image = read_image(path)
    channels = 1 if image.ndim == 2 else image.shape[2]
    if image.shape[:2] != tuple(manifest.projector) or channels != manifest.channels:
        raise AcquisitionError(
            f"pattern image of shape {image.shape}, not the {manifest.projector[0]}x"
            f"{manifest.projector[1]} {'grey' if manifest.channels == 1 else 'RGB'} image "
            "its manifest lists", path)
    return image


def simulate_captures(scene_path, patterns, output, *, camera, noise=0.0,
                      black: float = 0.0, gamma: float = 1.0, fmt: str = "png16", seed: int = 0,
                      progress: bool | None = None, rig: NonlinearRig | None = None,
                      exposures: Sequence[float] = (1.0,)) -> CameraModel:
    """Write the captures of every pattern of ``patterns`` for the scene at ``scene_path``.

    Parameters
    ----------
    scene_path : a store written by ``bigT scene``, or any transport store with an image
        shape (its T maps the projector's super-pixel grid, which must be the store's
        image shape); a colour T (3 channels) for a colour pattern set
    patterns : the pattern folder
    output : the captures folder (created; existing captures of the same names replaced;
        not the pattern folder, whose patterns have the captures' names)
    camera : (int, int), the camera's (Hc, Wc)
    noise : float, or three (R, G, B) for colour: the camera's noise std
    black, gamma : the camera's black level and gamma
    fmt : one of :data:`FORMATS` (with a rig: ``png8`` or ``png16``, its bits)
    seed : of the noise
    rig : NonlinearRig, optional
        A nonlinear projector and camera (module docstring) instead of the linear ones;
        ``noise``, ``black`` and ``gamma`` are the linear camera's and must stay 0, 0, 1.
    exposures : sequence of float, seconds, rising
        The rig's exposure bracket (one: single captures ``<pattern>.png``).

    Returns
    -------
    CameraModel
    """
    manifest = read_manifest(patterns)
    if Path(output).resolve() == patterns_folder(patterns).resolve():
        raise AcquisitionError(
            "the captures folder is the pattern folder: the captures, named as the "
            "patterns, would overwrite them; write the captures to a folder of their own",
            Path(output))
    T = open_store(scene_path)  # only T and its pixel order: a scene's ground truth unread
    order = T.pixel_order
    if order is None or tuple(order.image_shape) != manifest.grid:
        shape = None if order is None else order.image_shape
        raise AcquisitionError(
            f"the patterns are for a {manifest.grid[0]}x{manifest.grid[1]} super-pixel grid "
            f"but the scene is {shape[0]}x{shape[1]} pixels" if shape else
            "the scene records no image shape", Path(patterns))
    _check_channels(order.channels, manifest.channels, Path(scene_path))
    if fmt not in FORMATS:
        raise AcquisitionError(f"unknown capture format {fmt!r} (one of {', '.join(FORMATS)})")
    noise = _checked_noise(noise, order.channels)
    exposures = _checked_rig(rig, exposures, fmt, noise, black, gamma)
    model = CameraModel(tuple(camera), manifest.grid, noise=noise, black=black, gamma=gamma)
    white = T.matmul(np.ones(order.n), order="matrix")
    sp = model.superpixel_of()
    brightest = order.to_images(white).reshape(order.pixels, -1).max(axis=1)  # of R, G, B
    peak = (model.gain() * np.where(sp >= 0, brightest[np.maximum(sp, 0)], 0)).max()
    # with a rig, the white pattern's brightest pixel fills PEAK of the full well in
    # the shortest exposure (its light at full scale is 1, r(1) = 1)
    model = CameraModel(model.camera, model.grid, PEAK / peak / exposures[0], noise, black,
                        gamma)
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    folder, suffix = Path(patterns), FORMATS[fmt]
    bits = 8 if fmt == "png8" else 16
    index = {p.stem: k for k, p in enumerate(manifest.patterns)}
    batches = [manifest.patterns[k:k + BATCH] for k in range(0, len(manifest.patterns), BATCH)]
    for batch in progress_bar(batches, progress=progress, desc="captures", unit="batch"):
        vectors = _pattern_vectors(manifest, folder, batch, order,
                                   None if rig is None else rig.project)
        light = order.to_images(T.matmul(vectors, order="matrix"))
        light = light.reshape(len(batch), *order.frame_shape)
        for p, image in zip(batch, model.render(light, rng)):
            if rig is None:
                write_image(out / (p.stem + suffix), image, bits=bits)
                continue
            for t in exposures:  # image: the radiance, per second
                name = p.stem + ("" if len(exposures) == 1 else f"@{t:g}") + suffix
                write_image(out / name, rig.capture(image, t, frame=index[p.stem]), bits=bits)
    record = {"scene": str(Path(scene_path).resolve()), "format": fmt, "seed": seed,
              **asdict(model)}
    if rig is not None:
        record.update(rig=rig_record(rig), exposures=list(exposures))
    with atomic_output(out / SIMULATION, "the simulation's camera model") as tmp:
        with open(tmp, "w") as f:
            json.dump(record, f, indent=1)
    return model


def rig_record(rig: NonlinearRig) -> dict:
    """The rig's parameters as ``simulation.json`` records them (``camera``: its
    response, as ``--camera-response`` spells it)."""
    camera = rig.camera
    spelt = {"linear": "linear", "srgb": "srgb"}.get(
        camera.kind, f"gamma:{camera.gamma:g}" if camera.kind == "gamma" else camera.describe())
    return {"projector_gamma": rig.projector_gamma, "projector_black": rig.projector_black,
            "projector_shoulder": rig.projector_shoulder, "camera_response": spelt,
            "full_well_electrons": rig.full_well_electrons, "read_noise": rig.read_noise,
            "bits": rig.bits}


def _checked_rig(rig: NonlinearRig | None, exposures, fmt: str, noise, black: float,
                 gamma: float) -> tuple[float, ...]:
    """The exposures, rising and positive; with a rig, the linear camera's settings at
    their defaults and the format the rig's PNG."""
    times = tuple(float(t) for t in exposures)
    if not times or not all(np.isfinite(t) and t > 0 for t in times) or any(
            b <= a for a, b in zip(times, times[1:])):
        raise AcquisitionError(f"exposures must be positive seconds, rising strictly, got "
                               f"{list(times)!r:.80}", option="exposures")
    if rig is None:
        if len(times) > 1:
            raise AcquisitionError(
                f"exposure brackets ({len(times)} exposures) are the nonlinear rig's: give its "
                "camera too ({option})",
                option=Option("rig", UNSET, python="rig=NonlinearRig(...)",
                              cli="--camera-response, --bits ..."))
        return times
    if np.any(np.asarray(noise)) or black or gamma != 1.0:
        raise AcquisitionError("noise, black and gamma are the linear camera's; the "
                               "nonlinear rig's noise is its full well and read noise, its "
                               "curve {option}", option="camera_response")
    if fmt != f"png{rig.bits}":
        raise AcquisitionError(f"the rig's {rig.bits}-bit camera writes png{rig.bits} "
                               f"captures, not {fmt}", option="format")
    return times


def _check_channels(store_channels: int, pattern_channels: int, path: Path) -> None:
    """A colour T needs a colour pattern set and a grey T a grey one."""
    if store_channels == pattern_channels:
        return
    if store_channels == 3:
        raise AcquisitionError("a colour transport (3 channels) and grey patterns: write the "
                               "patterns with {option}", path, option=("channels", 3))
    raise AcquisitionError("a grey transport and colour patterns (channels 3): write the "
                           "patterns with {option}, or simulate a colour transport", path,
                           option=("channels", 1))


def _checked_noise(noise, channels: int) -> float | tuple[float, ...]:
    """``noise`` as a float, or a tuple of one std per channel of a colour T."""
    values = np.atleast_1d(np.asarray(noise, dtype=np.float64))
    if values.ndim != 1 or len(values) not in (1, channels) or (values < 0).any() or not \
            np.isfinite(values).all():
        raise AcquisitionError(f"noise must be one std >= 0 or one for each of the "
                               f"{channels} channels, got {noise!r:.60}", option="noise")
    return float(values[0]) if len(values) == 1 else tuple(float(v) for v in values)


def read_camera_model(captures) -> CameraModel:
    """The camera model a simulation wrote beside its captures."""
    path = Path(captures) / SIMULATION
    try:
        d = json.loads(path.read_text())
        noise = tuple(d["noise"]) if isinstance(d["noise"], list) else d["noise"]
        return CameraModel(tuple(d["camera"]), tuple(d["grid"]), d["exposure"], noise,
                           d["black"], d["gamma"])
    except (OSError, ValueError, KeyError) as exc:
        raise AcquisitionError(f"no readable simulation record ({exc})", path) from None
