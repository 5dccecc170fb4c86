"""Camera and matrices, built in float64 relative to the ring's origin.

Positions on the GPU are float32 offsets from a float64 origin; the view-projection
matrix is computed here in float64 for offsets from that same origin, so a scene at
x = 6.4e5 renders exactly like the same scene at x = 0 (the large numbers cancel on the
CPU in float64 before anything is rounded to float32).

Conventions (all tiers): right-handed world, column vectors (``clip = M @ [p, 1]``),
clip depth in [0, 1] (WebGPU), pixel (0, 0) is the top-left corner and the centre of
pixel (i, j) is (i + 0.5, j + 0.5). Frustum planes are (a, b, c, d) with
``a*x + b*y + c*z + d >= 0`` inside; a point exactly on a plane is inside.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Optional

import numpy as np


def _normalize(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v)
    return v / n if n > 0 else v


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of two 3-vectors, the same products and differences (np.cross's argument
    handling costs ~20 us a call, and every frame builds its matrices)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    f = _normalize(target - eye)
    if abs(np.dot(f, _normalize(up))) > 0.999:  # looking along up: pick another up
        up = np.array([0.0, 1.0, 0.0]) if abs(f[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    s = _normalize(_cross(f, up))
    u = _cross(s, f)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = s, u, -f
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def perspective(fov_y_deg: float, aspect: float, near: float, far: float) -> np.ndarray:
    """Depth in [0, 1] (WebGPU/D3D convention)."""
    f = 1.0 / np.tan(np.radians(fov_y_deg) / 2.0)
    m = np.zeros((4, 4))
    m[0, 0] = f / aspect
    m[1, 1] = f
    m[2, 2] = far / (near - far)
    m[2, 3] = near * far / (near - far)
    m[3, 2] = -1.0
    return m


@dataclass
class Camera:
    eye: np.ndarray
    target: np.ndarray
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    fov_deg: float = 60.0
    near: float = 0.1
    far: float = 10_000.0

    def __post_init__(self) -> None:
        self.eye = np.asarray(self.eye, np.float64)
        self.target = np.asarray(self.target, np.float64)
        self.up = np.asarray(self.up, np.float64)

    def view(self, origin=None) -> np.ndarray:
        """View matrix for coordinates relative to ``origin`` (float64)."""
        o = np.zeros(3) if origin is None else np.asarray(origin, np.float64)
        return look_at(self.eye - o, self.target - o, self.up)

    def proj(self, width: int, height: int) -> np.ndarray:
        return perspective(self.fov_deg, width / max(height, 1), self.near, self.far)

    def view_proj(self, width: int, height: int, origin=None) -> np.ndarray:
        """float64 4x4: origin-relative position -> clip space."""
        return self.proj(width, height) @ self.view(origin)

    def frustum_planes(self, width: int, height: int, origin=None) -> np.ndarray:
        """(6, 4) float64 planes (left, right, bottom, top, near, far), normalised, in
        origin-relative coordinates; derived from the matrix (Gribb-Hartmann, z in [0, 1])."""
        return planes_of(self.view_proj(width, height, origin))

    def translated(self, offset) -> "Camera":
        o = np.asarray(offset, np.float64)
        return replace(self, eye=self.eye + o, target=self.target + o)

    @classmethod
    def fit(cls, lo, hi, *, fov_deg: float = 60.0, azimuth_deg: float = -60.0,
            elevation_deg: float = 35.0, up=(0.0, 0.0, 1.0), aspect: float = 16 / 9) -> "Camera":
        """Frame the box [lo, hi] (world coordinates, float64) from the given direction."""
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        centre = (lo + hi) / 2.0
        radius = max(float(np.linalg.norm(hi - lo)) / 2.0, 1e-3)
        half = np.radians(fov_deg) / 2.0
        half = min(half, np.arctan(np.tan(half) * aspect))
        dist = radius / np.sin(half) * 0.85
        az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
        d = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        return cls(eye=centre + d * dist, target=centre, up=np.asarray(up, np.float64),
                   fov_deg=fov_deg, near=max(dist - radius * 1.5, dist * 1e-3), far=dist + radius * 1.5)


#: The near plane is never closer than this share of the far plane. Every tier orders points by
#: their linear view depth (float32 ``w`` keys, the quads method's ``w * 2^-k``, gl's
#: ``(w - near) / (far - near)``), so a near plane this close costs no depth precision; it only
#: keeps the frustum's near test meaningful.
NEAR_FLOOR = 1e-7

#: Map and live points whose boxes lie further apart than this many times the larger box's
#: size are "apart": the auto camera frames the map alone (docs/map.md).
APART_FACTOR = 10.0

Box = tuple  # (lo, hi): float64 world corners


def _corners(lo, hi) -> np.ndarray:
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def clip_planes(eye, target, up, fov_deg: float, aspect: float, boxes) -> tuple[float, float]:
    """Near and far planes from what lies in front of the camera: of every box ``(lo, hi)``
    (world float64) that is not wholly outside one side plane of the view, the nearest and
    farthest corner along the view axis (near halved, far 5 % further; the near plane at least
    :data:`NEAR_FLOOR` of the far). A box behind the eye or beside the view plays no part, so a
    georeferenced map far from the live points does not push the planes away from either.
    Nothing in view: a range around the target."""
    eye = np.asarray(eye, np.float64)
    view = look_at(np.zeros(3), np.asarray(target, np.float64) - eye, np.asarray(up, np.float64))[:3, :3]
    ty = math.tan(math.radians(float(fov_deg)) / 2.0)
    tx = ty * float(aspect)
    lo_d, hi_d = math.inf, 0.0
    for box in boxes:
        if box is None:
            continue
        v = (_corners(*box) - eye) @ view.T  # eye space: the camera looks down -z
        d = -v[:, 2]
        if (d <= 0).all() or (v[:, 0] > d * tx).all() or (v[:, 0] < -d * tx).all() \
                or (v[:, 1] > d * ty).all() or (v[:, 1] < -d * ty).all():
            continue
        lo_d, hi_d = min(lo_d, max(float(d.min()), 0.0)), max(hi_d, float(d.max()))
    if not hi_d > 0:
        dist = float(np.linalg.norm(np.asarray(target, np.float64) - eye)) or 1.0
        return dist * 1e-3, dist * 100.0
    far = hi_d * 1.05 + 1e-6
    return max(lo_d * 0.5, far * NEAR_FLOOR), far


def box_gap(a: Box, b: Box) -> float:
    """Distance between two boxes (0 when they touch or overlap)."""
    (alo, ahi), (blo, bhi) = ((np.asarray(x, np.float64) for x in box) for box in (a, b))
    gap = np.maximum(0.0, np.maximum(alo - bhi, blo - ahi))
    return float(np.linalg.norm(gap))


def box_size(box: Box) -> float:
    return float(np.linalg.norm(np.asarray(box[1], np.float64) - np.asarray(box[0], np.float64)))


def scene_box(live: Optional[Box], map_box: Optional[Box]) -> tuple[Optional[Box], float]:
    """What the auto camera frames, and how far apart map and live points are (0 unless they are
    *apart*: further than :data:`APART_FACTOR` times the larger box's size). Apart, the map
    alone is framed: both at once would be two dots."""
    if map_box is None or live is None:
        return (live if map_box is None else map_box), 0.0
    gap = box_gap(live, map_box)
    if gap > APART_FACTOR * max(box_size(live), box_size(map_box), 1.0):
        return map_box, gap
    lo = np.minimum(np.asarray(live[0], np.float64), np.asarray(map_box[0], np.float64))
    hi = np.maximum(np.asarray(live[1], np.float64), np.asarray(map_box[1], np.float64))
    return (lo, hi), 0.0


def project_to_pixels(points_rel: np.ndarray, view_proj: np.ndarray, width: int, height: int):
    """Reference projection (float64): returns (px, py, depth, w) with the tier conventions."""
    p = np.asarray(points_rel, np.float64)
    clip = p @ view_proj[:3, :3].T + view_proj[:3, 3]
    w = p @ view_proj[3, :3] + view_proj[3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        ndc = clip / w[:, None]
    px = (ndc[:, 0] * 0.5 + 0.5) * width
    py = (0.5 - ndc[:, 1] * 0.5) * height
    return px, py, ndc[:, 2], w


class OrbitController:
    """Turns mouse motion into a new :class:`Camera` (orbit about the target, pan, dolly).

    Angles are in the camera's up frame; the distance never collapses to zero."""

    def __init__(self, camera: Camera, *, orbit_deg_per_px: float = 0.3, zoom_per_wheel: float = 1.0015):
        self.camera = camera
        self.orbit_deg_per_px = orbit_deg_per_px
        self.zoom_per_wheel = zoom_per_wheel

    def _frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        c = self.camera
        up = c.up / (np.linalg.norm(c.up) or 1.0)
        off = c.eye - c.target
        dist = float(np.linalg.norm(off)) or 1e-6
        fwd = -off / dist
        right = np.cross(fwd, up)
        if np.linalg.norm(right) < 1e-9:
            right = np.cross(fwd, np.array([1.0, 0.0, 0.0]))
        right /= np.linalg.norm(right)
        return up, right, np.cross(right, fwd), dist

    def orbit(self, dx_px: float, dy_px: float) -> Camera:
        c = self.camera
        up, right, _, dist = self._frame()
        off = c.eye - c.target
        az = math.radians(-dx_px * self.orbit_deg_per_px)
        el = math.radians(dy_px * self.orbit_deg_per_px)
        off = _rotate(off, up, az)
        # clamp elevation so we never flip over the pole
        cur = math.asin(max(-1.0, min(1.0, float(np.dot(off / dist, up)))))
        el = max(-math.radians(89) - cur, min(math.radians(89) - cur, el))
        right = np.cross(-off / dist, up)
        if np.linalg.norm(right) > 1e-9:
            off = _rotate(off, right / np.linalg.norm(right), el)
        self.camera = Camera(eye=c.target + off, target=c.target.copy(), up=c.up, fov_deg=c.fov_deg,
                             near=c.near, far=c.far)
        return self.camera

    def pan(self, dx_px: float, dy_px: float, height_px: int) -> Camera:
        c = self.camera
        _, right, cam_up, dist = self._frame()
        world_per_px = 2.0 * dist * math.tan(math.radians(c.fov_deg) / 2.0) / max(height_px, 1)
        move = (-dx_px * right + dy_px * cam_up) * world_per_px
        self.camera = Camera(eye=c.eye + move, target=c.target + move, up=c.up, fov_deg=c.fov_deg,
                             near=c.near, far=c.far)
        return self.camera

    def zoom(self, wheel_dy: float) -> Camera:
        c = self.camera
        f = self.zoom_per_wheel ** float(wheel_dy)
        off = (c.eye - c.target) * f
        if np.linalg.norm(off) < 1e-6:
            off = (c.eye - c.target)
        self.camera = Camera(eye=c.target + off, target=c.target.copy(), up=c.up, fov_deg=c.fov_deg,
                             near=c.near * f, far=c.far * f)
        return self.camera


def _rotate(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues rotation of v about a unit axis."""
    k = axis / (np.linalg.norm(axis) or 1.0)
    return v * math.cos(angle) + np.cross(k, v) * math.sin(angle) + k * np.dot(k, v) * (1 - math.cos(angle))


def planes_of(m: np.ndarray) -> np.ndarray:
    """:meth:`Camera.frustum_planes` of a view-projection matrix already at hand."""
    r0, r1, r2, r3 = np.asarray(m, np.float64)
    planes = np.array([r3 + r0, r3 - r0, r3 + r1, r3 - r1, r2, r3 - r2])
    planes /= np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
    return planes
