"""A camera without a rig: ``bigT acquire simulate`` (:func:`simulate_captures`).

Renders, from a synthetic scene's T, the image a camera of another resolution would
capture for each pattern:

* the camera frames the projected area with a margin (:data:`MARGIN` of each side sees
  no projector light) and a smooth warp (lens and perspective), so each projector
  super-pixel is seen by a patch of camera pixels of uneven size and shape;
* a smooth, uneven gain over the frame (vignetting and surface orientation);
* an exposure that puts the brightest pixel of the white pattern at :data:`PEAK`;
* additive Gaussian noise, a black level, and optionally a gamma (stored = linear^(1/g)),
  then the file format's quantisation (16-bit PNG by default).

The camera's model is written beside the captures as ``simulation.json`` (a file bigT
acquire build ignores), so the T a build recovers can be compared with
``exposure * diag(mean gain of each group) * T_scene`` (:meth:`CameraModel.expected_scale`).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..atomic import atomic_output
from ..errors import AcquisitionError
from ..images import read_image, write_image
from ..progress import progress_bar
from ..storage import PixelOrder
from .correspondence import Correspondence
from .manifest import Manifest, patterns_folder, read_manifest

MARGIN = 0.05
PEAK = 0.9
WARP = 0.12  # amplitude of the warp, in super-pixels
SIMULATION = "simulation.json"
FORMATS = {"png16": ".png", "png8": ".png", "tif": ".tif", "npy": ".npy"}
BATCH = 64


@dataclass(frozen=True)
class CameraModel:
    """Where each camera pixel looks, and with which gain.

    Attributes
    ----------
    camera : (int, int), (Hc, Wc)
    grid : (int, int), the projector's super-pixel grid
    exposure : float, multiplies every capture's light
    noise, black, gamma : float
    """

    camera: tuple[int, int]
    grid: tuple[int, int]
    exposure: float = 1.0
    noise: float = 0.0
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
        recovers T_scene with."""
        # the same group means a build takes, over the true correspondence
        groups = Correspondence(self.superpixel_of(), self.grid, "simulation").reducer(order)
        return self.exposure * groups(self.gain())

    def render(self, light: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Camera images of scene light.

        Parameters
        ----------
        light : ndarray, shape (K, gh, gw), T l of K patterns as grid images

        Returns
        -------
        ndarray, shape (K, Hc, Wc), float64, stored values (gamma-encoded, unclipped)
        """
        sp = self.superpixel_of()
        seen = np.where(sp >= 0, light.reshape(len(light), -1)[:, np.maximum(sp, 0)], 0.0)
        linear = self.exposure * self.gain() * seen + self.black
        if self.noise:
            linear = linear + rng.normal(0.0, self.noise, size=linear.shape)
        if self.gamma != 1.0:
            linear = np.power(np.maximum(linear, 0.0), 1.0 / self.gamma)
        return linear


def _pattern_vectors(manifest: Manifest, folder: Path, patterns, order: PixelOrder) -> np.ndarray:
    """The projector images of ``patterns``, averaged over super-pixels, in matrix order:
    (n, K)."""
    s = manifest.superpixel
    gh, gw = manifest.grid
    images = np.stack([read_image(folder / p.file, manifest.projector)
                       .reshape(gh, s, gw, s).mean(axis=(1, 3)) for p in patterns])
    return order.to_matrix(images)


def simulate_captures(scene_path, patterns, output, *, camera, noise: float = 0.0,
                      black: float = 0.0, gamma: float = 1.0, fmt: str = "png16", seed: int = 0,
                      progress: bool | None = None) -> CameraModel:
    """Write the captures of every pattern of ``patterns`` for the scene at ``scene_path``.

    Parameters
    ----------
    scene_path : a store written by ``bigT scene`` (its T maps the projector's
        super-pixel grid, which must be the scene's image shape)
    patterns : the pattern folder
    output : the captures folder (created; existing captures of the same names replaced;
        not the pattern folder, whose patterns have the captures' names)
    camera : (int, int), the camera's (Hc, Wc)
    noise, black, gamma : the camera's noise std, black level and gamma
    fmt : one of :data:`FORMATS`
    seed : of the noise

    Returns
    -------
    CameraModel
    """
    from ..scenes import load  # scenes import the engine and dask (~0.5 s): only the
    # simulated camera reads a scene

    manifest = read_manifest(patterns)
    if Path(output).resolve() == patterns_folder(patterns).resolve():
        raise AcquisitionError(
            "the captures folder is the pattern folder: the captures, named as the "
            "patterns, would overwrite them; write the captures to a folder of their own",
            Path(output))
    scene = load(scene_path)
    order = scene.pixel_order
    if order is None or tuple(order.image_shape) != manifest.grid:
        shape = None if order is None else order.image_shape
        raise AcquisitionError(
            f"the patterns are for a {manifest.grid[0]}x{manifest.grid[1]} super-pixel grid "
            f"but the scene is {shape[0]}x{shape[1]} pixels" if shape else
            "the scene records no image shape", Path(patterns))
    if fmt not in FORMATS:
        raise AcquisitionError(f"unknown capture format {fmt!r} (one of {', '.join(FORMATS)})")
    model = CameraModel(tuple(camera), manifest.grid, noise=noise, black=black, gamma=gamma)
    white = scene.T.matmul(np.ones(order.n), order="matrix")
    peak = (model.gain() * np.where(model.superpixel_of() >= 0,
                                    order.to_images(white).ravel()[np.maximum(model.superpixel_of(), 0)],
                                    0)).max()
    model = CameraModel(model.camera, model.grid, PEAK / peak, noise, black, gamma)
    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    folder, suffix = Path(patterns), FORMATS[fmt]
    batches = [manifest.patterns[k:k + BATCH] for k in range(0, len(manifest.patterns), BATCH)]
    for batch in progress_bar(batches, progress=progress, desc="captures", unit="batch"):
        light = order.to_images(scene.T.matmul(_pattern_vectors(manifest, folder, batch, order),
                                                order="matrix"))
        light = light.reshape(len(batch), *manifest.grid)
        for p, image in zip(batch, model.render(light, rng)):
            write_image(out / (p.stem + suffix), image, bits=8 if fmt == "png8" else 16)
    with atomic_output(out / SIMULATION, "the simulation's camera model") as tmp:
        with open(tmp, "w") as f:
            json.dump({"scene": str(Path(scene_path).resolve()), "format": fmt, "seed": seed,
                       **asdict(model)}, f, indent=1)
    return model


def read_camera_model(captures) -> CameraModel:
    """The camera model a simulation wrote beside its captures."""
    path = Path(captures) / SIMULATION
    try:
        d = json.loads(path.read_text())
        return CameraModel(tuple(d["camera"]), tuple(d["grid"]), d["exposure"], d["noise"],
                           d["black"], d["gamma"])
    except (OSError, ValueError, KeyError) as exc:
        raise AcquisitionError(f"no readable simulation record ({exc})", path) from None
