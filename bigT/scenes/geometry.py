"""Scene geometry: what each camera pixel sees, as a surface patch.

A pinhole projector and a pinhole camera sit together at the origin and look along
+z (paper §6.1: the projector's pixels are made to coincide with camera super-pixels,
so pixel i of the image is patch i of the scene). Each pixel's ray is cast into the
scene; the first surface it meets gives the patch: centre, unit normal facing the
camera, and area (the pixel's footprint on the surface).

Image coordinates: pixel (r, c) of an (H, W) image looks along (u, v, 1) with
``u = (c + 0.5 - W/2) s``, ``v = (r + 0.5 - H/2) s`` and ``s = 2 tan(fov/2) / W``
(square pixels, ``fov`` the horizontal field of view). Its solid angle is
``s^2 / (1 + u^2 + v^2)^(3/2)``, so a patch at distance d seen under the incidence
cosine cos_t has area ``omega d^2 / cos_t``.

All arrays are in row-major pixel order here; the caller renumbers them into the
store's pixel order.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import ShapeMismatchError

#: Incidence cosines below this are clamped when computing a patch's footprint area
#: (a ray grazing a sphere's silhouette would otherwise give an unbounded area).
MIN_VIEW_COSINE = 0.05


@dataclass
class Patches:
    """Surface patches seen by the pixels of an (H, W) image, row-major order.

    Attributes
    ----------
    points : ndarray, (n, 3) float64
        Patch centres.
    normals : ndarray, (n, 3) float64
        Unit normals, facing the camera.
    areas : ndarray, (n,) float64
        Patch areas (pixel footprints).
    view_cos : ndarray, (n,) float64
        Cosine between the normal and the direction back to the projector/camera.
    distance : ndarray, (n,) float64
        Distance from the projector/camera centre.
    face : ndarray, (n,) int32
        Which surface each patch lies on (for previews and tests).
    spheres : ndarray, (S, 4) float64
        Occluders (cx, cy, cz, radius) tested for visibility between patches; empty
        when no surface can hide another from a patch.
    reference_distance : float
        Distance at which a frontal patch gets first-bounce gain 1.
    same_face_exchange : bool
        Whether two patches of one face may see each other (a concave face); True
        unless the face is known planar or convex. The built-in scenes' faces all
        are, so their builders set False and the form factors search other faces only.
    """

    points: np.ndarray
    normals: np.ndarray
    areas: np.ndarray
    view_cos: np.ndarray
    distance: np.ndarray
    face: np.ndarray
    reference_distance: float
    spheres: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    same_face_exchange: bool = True

    @property
    def n(self) -> int:
        return int(self.points.shape[0])

    def take(self, order: np.ndarray) -> "Patches":
        """The patches renumbered: patch k of the result is patch order[k]."""
        return Patches(self.points[order], self.normals[order], self.areas[order],
                       self.view_cos[order], self.distance[order], self.face[order],
                       self.reference_distance, self.spheres, self.same_face_exchange)

    def first_bounce_gain(self) -> np.ndarray:
        """Projector irradiance per unit intensity: cos_t (d_ref / d)^2, shape (n,)."""
        return self.view_cos * (self.reference_distance / self.distance) ** 2


def camera_rays(size: tuple[int, int], fov_deg: float):
    """Unit ray directions (H*W, 3) in row-major order and their solid angles (H*W,)."""
    H, W = (int(s) for s in size)
    if H < 1 or W < 1:
        raise ShapeMismatchError(f"size must be (H, W) with H, W >= 1, got {size}")
    s = 2.0 * np.tan(np.radians(fov_deg) / 2.0) / W
    v, u = np.meshgrid((np.arange(H) + 0.5 - H / 2.0) * s, (np.arange(W) + 0.5 - W / 2.0) * s,
                       indexing="ij")
    d = np.stack([u.ravel(), v.ravel(), np.ones(H * W)], axis=1)
    norm = np.linalg.norm(d, axis=1)
    omega = s * s / norm ** 3
    return d / norm[:, None], omega


def _patches(rays, omega, t, normals, face, d_ref, spheres=None) -> Patches:
    points = rays * t[:, None]
    cos_t = np.clip(-(normals * rays).sum(axis=1), 0.0, 1.0)
    areas = omega * t * t / np.maximum(cos_t, MIN_VIEW_COSINE)
    # every face built here is a plane or a convex hemisphere: no light within a face
    return Patches(points, normals, areas, cos_t, t.copy(), face.astype(np.int32), d_ref,
                   np.zeros((0, 4)) if spheres is None else spheres, same_face_exchange=False)


def wall_corner(size, *, concave=True, distance=1.0, fov_deg=60.0) -> Patches:
    """Two walls meeting at 90 degrees along a vertical fold on the optical axis.

    The fold is at depth ``distance``; the image is split across it at column W/2.
    ``concave=True``: the fold is the farthest line and the walls face each other
    (interreflection); ``concave=False``: the fold is nearest, the walls face away
    from each other, no light passes between them.
    """
    rays, omega = camera_rays(size, fov_deg)
    ux = rays[:, 0] / rays[:, 2]
    left = ux < 0
    r2 = np.sqrt(0.5)
    if concave:
        # left wall z = D + x (x < 0), right wall z = D - x (x > 0)
        t_over_z = distance / (1.0 + np.abs(ux))
        normals = np.where(left[:, None], [r2, 0.0, -r2], [-r2, 0.0, -r2])
    else:
        if np.abs(ux).max() >= 1.0:
            raise ShapeMismatchError("the convex corner needs a field of view below 90 degrees")
        t_over_z = distance / (1.0 - np.abs(ux))
        normals = np.where(left[:, None], [-r2, 0.0, -r2], [r2, 0.0, -r2])
    t = t_over_z / rays[:, 2]
    return _patches(rays, omega, t, normals.astype(np.float64), (~left).astype(np.int32), distance)


def flat_wall(size, *, distance=1.0, fov_deg=60.0) -> Patches:
    """A frontal plane z = ``distance``."""
    rays, omega = camera_rays(size, fov_deg)
    t = distance / rays[:, 2]
    normals = np.tile([0.0, 0.0, -1.0], (rays.shape[0], 1))
    return _patches(rays, omega, t, normals, np.zeros(rays.shape[0], np.int32), distance)


def cornell_box(size, *, opening_distance=2.0, depth=2.0) -> Patches:
    """An open box seen through its missing front face (paper Fig. 4b).

    The box is ``|x| <= X``, ``|y| <= 1``, ``z0 <= z <= z0 + depth`` with X the image's
    aspect ratio W/H, so the image exactly fills the opening. Faces: 0 back, 1 left,
    2 right, 3 top, 4 bottom; normals point into the box.
    """
    H, W = (int(s) for s in size)
    X, Y, z0 = W / H, 1.0, float(opening_distance)
    fov = 2.0 * np.degrees(np.arctan(X / z0))
    rays, omega = camera_rays(size, fov)
    dx, dy, dz = rays.T
    big = np.inf
    with np.errstate(divide="ignore"):
        cand = np.stack([
            (z0 + depth) / dz,
            np.where(dx < 0, -X / dx, big),
            np.where(dx > 0, X / dx, big),
            np.where(dy < 0, -Y / dy, big),
            np.where(dy > 0, Y / dy, big),
        ], axis=1)
    face = np.argmin(cand, axis=1)
    t = cand[np.arange(len(face)), face]
    face_normals = np.array([[0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], float)
    return _patches(rays, omega, t, face_normals[face], face, z0 + depth / 2.0)


def hemisphere_field(size, *, distance=3.0, fov_deg=60.0, across=5, radius_fraction=0.42) -> Patches:
    """A frontal plane z = ``distance`` tiled with hemispheres bulging toward the camera
    (paper Fig. 1): ``across`` hemispheres per image width on a square grid, radius
    ``radius_fraction`` of the grid pitch. The spheres occlude each other and the plane.
    """
    H, W = (int(s) for s in size)
    rays, omega = camera_rays(size, fov_deg)
    half_w = distance * np.tan(np.radians(fov_deg) / 2.0)
    half_h = half_w * H / W
    pitch = 2.0 * half_w / across
    R = radius_fraction * pitch
    nx = across
    ny = max(1, int(round(2.0 * half_h / pitch)))
    cx = (np.arange(nx) + 0.5 - nx / 2.0) * pitch
    cy = (np.arange(ny) + 0.5 - ny / 2.0) * pitch
    CX, CY = np.meshgrid(cx, cy)
    centres = np.stack([CX.ravel(), CY.ravel(), np.full(CX.size, distance)], axis=1)
    t = distance / rays[:, 2]
    face = np.zeros(rays.shape[0], np.int32)
    for k, c in enumerate(centres):
        b = rays @ c
        disc = b * b - (c @ c - R * R)
        ok = disc >= 0
        t1 = np.where(ok, b - np.sqrt(np.where(ok, disc, 0.0)), np.inf)
        z1 = t1 * rays[:, 2]
        hit = ok & (t1 > 0) & (z1 <= distance) & (t1 < t)
        t = np.where(hit, t1, t)
        face = np.where(hit, k + 1, face)
    points = rays * t[:, None]
    normals = np.tile([0.0, 0.0, -1.0], (rays.shape[0], 1))
    on = face > 0
    normals[on] = (points[on] - centres[face[on] - 1]) / R
    spheres = np.concatenate([centres, np.full((len(centres), 1), R)], axis=1)
    return _patches(rays, omega, t, normals, face, distance, spheres)
