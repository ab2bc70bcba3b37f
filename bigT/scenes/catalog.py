"""The scenes there are and their presets: names only, cheap to import (the CLI lists
them in its help without loading the builder, scipy.spatial and zarr)."""

from __future__ import annotations

from .. import config

#: Density presets: (form-factor cut, T threshold). "exact" keeps every pair and every
#: bounce (small scenes only: all n^2 pairs are tested).
DENSITIES = {
    "exact": (0.0, 0.0),
    "sparse": (config.SCENE_SPARSE_FF_CUT, config.SCENE_SPARSE_THRESHOLD),
    "dense": (config.SCENE_DENSE_FF_CUT, config.SCENE_DENSE_THRESHOLD),
}

SCENE_NAMES = ("dihedral4", "corner", "convex", "flat", "cornell", "hemispheres")

#: Default image size of each scene; cornell's gives the paper's 5120 patches.
DEFAULT_SIZES = {"corner": (96, 128), "convex": (96, 128), "flat": (96, 128),
                 "cornell": (64, 80), "hemispheres": (96, 128)}
