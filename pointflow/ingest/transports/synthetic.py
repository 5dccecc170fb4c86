"""``synthetic``: a procedural town swept by a simulated spinning lidar.

Needs no data, no network and no display, so the demo, the tests and the benchmarks
all use it. The scene (deterministic given ``seed``): a ground plane with two crossing
roads (dark asphalt, bright lane markings, grass verges), blocks of buildings (boxes with
window bands), street trees (trunk cylinder + ellipsoid crown), lamp posts, parked cars,
and a few cars driving along the roads. The sensor drives up and down the main road
(``drive_speed``, ``sensor_height`` above the ground) with ``beams`` lasers spread over ``vertical_fov`` and turns at
``scan_hz``; every turn fires ``points_per_scan`` rays (rounded up to whole firings of all
beams), cut into ``chunks_per_scan``
azimuth sectors that are released at the time the real sensor would have finished them
(``realtime``), ``rate`` times faster, or as fast as possible.

Rays are cast against the analytic primitives with numpy (rays x primitives arrays, only
the primitives inside the sector's azimuth range), so there is no per-point Python work.
Rays that hit nothing within ``max_range`` (the sky) give no return, as on a real sensor.

Channels: ``intensity`` (float32, 0..255: (reflectance x incidence x range falloff)^0.6
+ noise), ``classification`` (uint8, LAS codes: 2 ground, 5 vegetation, 6 building,
1 other, 11 road), ``beam`` (uint16 laser index), ``range`` (float32 metres).
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, Iterator, Literal, Optional

import numpy as np

from ...chunk import PointChunk
from ...frames.message import Transform, Transforms
from ...typed import ConfigError
from .base import Transport

CHANNELS = ("intensity", "classification", "beam", "range")

# LAS classification codes used for the scene's materials.
C_OTHER, C_GROUND, C_VEG, C_BUILDING, C_ROAD = 1, 2, 5, 6, 11


@dataclasses.dataclass
class SyntheticOptions:
    scan_hz: float = 10.0
    points_per_scan: int = 100_000
    chunks_per_scan: int = 10
    beams: int = 32
    #: [lowest, highest] beam elevation in degrees.
    vertical_fov: list[float] = dataclasses.field(default_factory=lambda: [-25.0, 15.0])
    max_range: float = 120.0
    min_range: float = 0.5
    sensor_height: float = 1.8
    #: Added to every position (float64), e.g. [637000, 851000, 0] to look georeferenced.
    origin: list[float] = dataclasses.field(default_factory=lambda: [0.0, 0.0, 0.0])
    #: Stop after this many scans; 0 = forever.
    scans: int = 0
    #: Speed-up over real time when ``realtime`` is true.
    rate: float = 1.0
    #: False = produce chunks as fast as possible (benchmarks).
    realtime: bool = True
    seed: int = 0
    #: Standard deviation of the range noise, metres.
    range_noise: float = 0.02
    #: Cars driving along the roads.
    moving_objects: int = 3
    #: Half-size of the town, metres.
    scene_size: float = 90.0
    #: The sensor drives up and down the east-west road at this speed (m/s); 0 = parked
    #: at the crossing. Moving, the ring accumulates a map of the street.
    drive_speed: float = 4.0
    channels: list[str] = dataclasses.field(default_factory=lambda: ["intensity", "classification"])
    #: > 0: compute only this many distinct scans and then replay them in a loop (cheap
    #: high-rate load for benchmarks; casting costs ~1 s of CPU per million rays).
    cache_scans: int = 0
    #: dtype of the positions sent: float64 keeps large ``origin`` offsets exact.
    positions_dtype: str = "float64"
    #: ``world``: points in world coordinates. ``moving``: points in the sensor's own frame
    #: (``lidar``, stamped), plus the transforms that place it: ``odom -> base_link`` at 20 Hz
    #: (the drive, with a gentle yaw sway) and a static ``base_link -> lidar``; with
    #: ``frames.fixed: odom`` ingest puts them back in place (docs/frames.md).
    mode: Literal["world", "moving"] = "world"


@dataclasses.dataclass
class _Prims:
    """Analytic primitives, one row each (structure of arrays)."""

    box_min: np.ndarray  # (B,3)
    box_max: np.ndarray  # (B,3)
    box_refl: np.ndarray  # (B,)
    box_cls: np.ndarray  # (B,) uint8
    box_window: np.ndarray  # (B,) bool: facade with window bands
    cyl: np.ndarray  # (C,5) cx, cy, r, z0, z1
    cyl_refl: np.ndarray
    cyl_cls: np.ndarray
    ell: np.ndarray  # (E,6) cx, cy, cz, rx(=ry), rz, porosity
    ell_refl: np.ndarray
    ell_cls: np.ndarray


def _build_scene(o: SyntheticOptions) -> tuple[_Prims, np.ndarray]:
    """Static primitives and the moving cars' parameters, deterministic from the seed."""
    rng = np.random.default_rng(o.seed)
    S = o.scene_size
    road_half = 6.0
    boxes: list[tuple] = []  # (min3, max3, refl, cls, window)
    parks: list[tuple] = []
    # Building blocks in the four quadrants between the roads.
    block = 18.0
    for qx in (-1, 1):
        for qy in (-1, 1):
            x = road_half + 4.0
            while x + 6 < S:
                y = road_half + 4.0
                while y + 6 < S:
                    if rng.random() < 0.6:
                        w = rng.uniform(8, block - 2)
                        d = rng.uniform(8, block - 2)
                        h = rng.uniform(5, 28) if rng.random() < 0.8 else rng.uniform(30, 45)
                        x0, y0 = x + rng.uniform(0, block - w), y + rng.uniform(0, block - d)
                        lo = np.array([x0, y0, 0.0]) * [qx, qy, 1]
                        hi = np.array([x0 + w, y0 + d, h]) * [qx, qy, 1]
                        boxes.append((np.minimum(lo, hi), np.maximum(lo, hi), rng.uniform(0.35, 0.75), C_BUILDING, True))
                    else:  # a park: a few trees
                        for _ in range(int(rng.integers(2, 6))):
                            cx = qx * (x + rng.uniform(2, block - 2))
                            cy = qy * (y + rng.uniform(2, block - 2))
                            parks.append((cx, cy))
                    y += block + 4
                x += block + 4
    # Parked cars along the kerbs.
    for _ in range(14):
        along = rng.uniform(-S + 10, S - 10)
        if abs(along) < road_half + 8:
            continue
        side = rng.choice([-1, 1]) * (road_half - 1.2)
        L, W, H = rng.uniform(3.8, 4.8), 1.8, rng.uniform(1.4, 1.7)
        if rng.random() < 0.5:
            c = np.array([along, side, 0.0]); half = np.array([L / 2, W / 2, 0])
        else:
            c = np.array([side, along, 0.0]); half = np.array([W / 2, L / 2, 0])
        boxes.append((c - half + [0, 0, 0.25], c + half + [0, 0, H], rng.uniform(0.5, 0.9), C_OTHER, False))
    cyl, cyl_refl, cyl_cls = [], [], []
    ell, ell_refl, ell_cls = [], [], []
    # Street trees and lamp posts on the verges.
    for axis in (0, 1):
        for side in (-1, 1):
            pos = -S + 8 + rng.uniform(0, 4)
            while pos < S - 8:
                if abs(pos) > road_half + 6:
                    off = side * (road_half + 2.0)
                    cx, cy = (pos, off) if axis == 0 else (off, pos)
                    if rng.random() < 0.7:
                        th = rng.uniform(2.0, 3.5)
                        cyl.append((cx, cy, rng.uniform(0.15, 0.3), 0.0, th + 0.5)); cyl_refl.append(0.3); cyl_cls.append(C_VEG)
                        rx = rng.uniform(1.8, 3.2)
                        ell.append((cx, cy, th + rx * 0.9, rx, rx * rng.uniform(0.9, 1.4), 0.6)); ell_refl.append(0.45); ell_cls.append(C_VEG)
                    else:
                        cyl.append((cx, cy, 0.12, 0.0, 7.0)); cyl_refl.append(0.95); cyl_cls.append(C_OTHER)
                pos += rng.uniform(9, 14)
    for cx, cy in parks:
        th = rng.uniform(2.0, 4.0)
        cyl.append((cx, cy, rng.uniform(0.2, 0.4), 0.0, th + 0.5)); cyl_refl.append(0.3); cyl_cls.append(C_VEG)
        rx = rng.uniform(2.2, 4.0)
        ell.append((cx, cy, th + rx * 0.9, rx, rx * rng.uniform(0.8, 1.3), 0.6)); ell_refl.append(0.45); ell_cls.append(C_VEG)
    prims = _Prims(
        box_min=np.array([b[0] for b in boxes], np.float64).reshape(-1, 3),
        box_max=np.array([b[1] for b in boxes], np.float64).reshape(-1, 3),
        box_refl=np.array([b[2] for b in boxes], np.float64),
        box_cls=np.array([b[3] for b in boxes], np.uint8),
        box_window=np.array([b[4] for b in boxes], bool),
        cyl=np.array(cyl, np.float64).reshape(-1, 5), cyl_refl=np.array(cyl_refl), cyl_cls=np.array(cyl_cls, np.uint8),
        ell=np.array(ell, np.float64).reshape(-1, 6), ell_refl=np.array(ell_refl), ell_cls=np.array(ell_cls, np.uint8),
    )
    # Moving cars: (axis, lane offset, speed m/s, phase).
    movers = np.array([(i % 2, (-1) ** i * 2.5, rng.uniform(6, 14) * rng.choice([-1, 1]), rng.uniform(0, 2 * S))
                       for i in range(o.moving_objects)], np.float64).reshape(-1, 4)
    return prims, movers


def _ang_extent(cx, cy, r, sx, sy):
    """Centre azimuth and half-width (radians) of circles seen from the sensor."""
    dx, dy = cx - sx, cy - sy
    d = np.hypot(dx, dy)
    half = np.where(d > r, np.arcsin(np.clip(r / np.maximum(d, 1e-9), 0, 1)), np.pi)
    return np.arctan2(dy, dx), half


def _in_sector(center, half, a0, a1):
    """Which circles overlap azimuth interval [a0, a1) (radians, any wrap)."""
    mid, hw = (a0 + a1) / 2, (a1 - a0) / 2
    delta = np.abs((center - mid + np.pi) % (2 * np.pi) - np.pi)
    return delta <= half + hw + 1e-6


class SyntheticTransport(Transport):
    """Simulated spinning lidar over a procedural town (see module docs)."""

    name = "synthetic"
    options_schema = SyntheticOptions

    @classmethod
    def declared_channels(cls, options: dict[str, Any], base_dir: str = ".") -> Optional[frozenset[str]]:
        return frozenset(options.get("channels") or ())

    @classmethod
    def check_options(cls, o: SyntheticOptions, path: str, base_dir: str) -> None:
        for key in ("scan_hz", "max_range", "rate", "scene_size"):
            if getattr(o, key) <= 0:
                raise ConfigError(f"{path}.{key}", f"must be > 0, got {getattr(o, key)!r}")
        for key in ("points_per_scan", "chunks_per_scan", "beams"):
            if getattr(o, key) < 1:
                raise ConfigError(f"{path}.{key}", f"must be >= 1, got {getattr(o, key)!r}")
        for key in ("scans", "min_range", "range_noise", "moving_objects", "sensor_height", "drive_speed", "cache_scans"):
            if getattr(o, key) < 0:
                raise ConfigError(f"{path}.{key}", f"must be >= 0, got {getattr(o, key)!r}")
        if o.min_range >= o.max_range:
            raise ConfigError(f"{path}.min_range", f"must be less than max_range ({o.max_range}), got {o.min_range}")
        if len(o.vertical_fov) != 2 or not -90 <= o.vertical_fov[0] <= o.vertical_fov[1] <= 90:
            raise ConfigError(f"{path}.vertical_fov", f"must be [low, high] degrees with -90 <= low <= high <= 90, got {o.vertical_fov!r}")
        if len(o.origin) != 3:
            raise ConfigError(f"{path}.origin", f"must be [x, y, z], got {o.origin!r}")
        bad = [c for c in o.channels if c not in CHANNELS]
        if bad:
            raise ConfigError(f"{path}.channels", f"unknown channel {bad[0]!r}; expected any of {', '.join(CHANNELS)}")
        if o.mode == "moving" and o.cache_scans:
            raise ConfigError(f"{path}.cache_scans", "must be 0 with mode: moving (a cached scan would be sent with a later pose)")
        if o.positions_dtype not in ("float32", "float64"):
            raise ConfigError(f"{path}.positions_dtype", f"must be float32 or float64, got {o.positions_dtype!r}")
        if o.chunks_per_scan > o.points_per_scan:
            raise ConfigError(f"{path}.chunks_per_scan", f"must be <= points_per_scan ({o.points_per_scan})")

    def __init__(self, options: dict[str, Any] | None = None, source_id: str = "synthetic"):
        opts = dict(dataclasses.asdict(SyntheticOptions()))
        opts.update(options or {})
        super().__init__(opts, source_id)
        self.o = SyntheticOptions(**opts)
        o = self.o
        self.lossless = not o.realtime
        self.prims, self.movers = _build_scene(o)
        self.origin = np.asarray(o.origin, np.float64)
        self.n_az = max(o.chunks_per_scan, int(math.ceil(o.points_per_scan / o.beams)))
        el = np.radians(np.linspace(o.vertical_fov[0], o.vertical_fov[1], o.beams))
        self._cos_el, self._sin_el = np.cos(el), np.sin(el)
        p = self.prims
        self._box_c = (p.box_min + p.box_max) / 2
        self._box_r = np.hypot(*(p.box_max - p.box_min)[:, :2].T) / 2
        self.counters = {"scans": 0, "rays": 0, "returns": 0}
        self._cache: dict[tuple[int, int], PointChunk] = {}

    # ------------------------------------------------------------------ scene at time t
    def sensor_at(self, t: float) -> np.ndarray:
        """Sensor position at scene time ``t``: back and forth along the x road, right lane."""
        o = self.o
        if o.drive_speed <= 0:
            return np.array([0.0, 0.0, o.sensor_height])
        span = 0.7 * o.scene_size
        u = (o.drive_speed * t / span) % 4.0  # 0..4: centre -> +span -> centre -> -span -> centre
        x = span * (u if u < 1 else 2 - u if u < 3 else u - 4)
        lane = -2.5 if (u < 1 or u >= 3) else 2.5
        return np.array([x, lane, o.sensor_height])

    def _movers_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        S = self.o.scene_size
        mins, maxs = [], []
        for axis, lane, speed, phase in self.movers:
            along = (phase + speed * t) % (2 * S) - S
            half = np.array([2.2, 0.9]) if axis == 0 else np.array([0.9, 2.2])
            c = np.array([along, lane]) if axis == 0 else np.array([lane, along])
            mins.append([c[0] - half[0], c[1] - half[1], 0.25])
            maxs.append([c[0] + half[0], c[1] + half[1], 1.6])
        return np.array(mins, np.float64).reshape(-1, 3), np.array(maxs, np.float64).reshape(-1, 3)

    def _cast(self, d: np.ndarray, s: np.ndarray, a0: float, a1: float, t: float, rng: np.random.Generator):
        """Nearest hit of rays ``d`` (M,3) from ``s`` against the primitives that overlap
        azimuths [a0, a1]: (range, normal, reflectance, class, window-facade flag)."""
        o = self.o
        M = d.shape[0]
        best = np.full(M, np.inf)
        normal = np.zeros((M, 3))
        refl = np.zeros(M)
        cls = np.zeros(M, np.uint8)
        window = np.zeros(M, bool)

        # ground plane z = 0
        with np.errstate(divide="ignore", invalid="ignore"):
            tg = np.where(d[:, 2] < -1e-9, -s[2] / d[:, 2], np.inf)
        hit = tg < best
        best[hit] = tg[hit]
        normal[hit] = (0.0, 0.0, 1.0)
        cls[hit] = C_GROUND

        # boxes (static buildings/cars in this sector + moving cars)
        p = self.prims
        sel = _in_sector(*_ang_extent(self._box_c[:, 0], self._box_c[:, 1], self._box_r, s[0], s[1]), a0, a1)
        mv_min, mv_max = self._movers_at(t)
        if len(mv_min):  # moving cars: culled like the static boxes
            mc = (mv_min + mv_max) / 2
            msel = _in_sector(*_ang_extent(mc[:, 0], mc[:, 1], np.full(len(mc), 2.5), s[0], s[1]), a0, a1)
            mv_min, mv_max = mv_min[msel], mv_max[msel]
        bmin = np.concatenate([p.box_min[sel], mv_min])
        bmax = np.concatenate([p.box_max[sel], mv_max])
        brefl = np.concatenate([p.box_refl[sel], np.full(len(mv_min), 0.8)])
        bcls = np.concatenate([p.box_cls[sel], np.full(len(mv_min), C_OTHER, np.uint8)])
        bwin = np.concatenate([p.box_window[sel], np.zeros(len(mv_min), bool)])
        if len(bmin):
            # slab test per axis on (M, B) arrays (reductions over a length-3 axis are slow)
            with np.errstate(divide="ignore", invalid="ignore"):
                inv = 1.0 / np.where(np.abs(d) < 1e-12, 1e-12, d)
                tmins, tnear, tfar = [], None, None
                for k in range(3):
                    t1 = (bmin[:, k] - s[k]) * inv[:, k:k + 1]
                    t2 = (bmax[:, k] - s[k]) * inv[:, k:k + 1]
                    lo, hi = np.minimum(t1, t2), np.maximum(t1, t2)
                    tmins.append(lo)
                    tnear = lo if tnear is None else np.maximum(tnear, lo)
                    tfar = hi if tfar is None else np.minimum(tfar, hi)
            ok = (tnear <= tfar) & (tnear > 0)
            tb = np.where(ok, tnear, np.inf)
            j = tb.argmin(axis=1)
            tj = tb[np.arange(M), j]
            hit = tj < best
            if hit.any():
                hi_idx = np.flatnonzero(hit)
                jh = j[hi_idx]
                best[hi_idx] = tj[hi_idx]
                # the face hit is the axis whose entry time is the latest
                ax = np.argmax(np.stack([tm[hi_idx, jh] for tm in tmins], axis=1), axis=1)
                nrm = np.zeros((hi_idx.size, 3))
                nrm[np.arange(hi_idx.size), ax] = -np.sign(d[hi_idx, ax])
                normal[hi_idx] = nrm
                refl[hi_idx] = brefl[jh]
                cls[hi_idx] = bcls[jh]
                window[hi_idx] = bwin[jh]

        # vertical cylinders (trunks, lamp posts)
        sel = _in_sector(*_ang_extent(p.cyl[:, 0], p.cyl[:, 1], p.cyl[:, 2], s[0], s[1]), a0, a1)
        if sel.any():
            c = p.cyl[sel]
            ox, oy = s[0] - c[:, 0], s[1] - c[:, 1]
            a = (d[:, 0] ** 2 + d[:, 1] ** 2)[:, None]
            b = 2 * (d[:, 0:1] * ox + d[:, 1:2] * oy)
            cc = ox ** 2 + oy ** 2 - c[:, 2] ** 2
            disc = b * b - 4 * a * cc
            with np.errstate(divide="ignore", invalid="ignore"):
                tc = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
            z = s[2] + tc * d[:, 2:3]
            tc = np.where((disc > 0) & (tc > 0) & (z >= c[:, 3]) & (z <= c[:, 4]), tc, np.inf)
            j = tc.argmin(axis=1)
            tj = tc[np.arange(M), j]
            hit = tj < best
            if hit.any():
                best[hit] = tj[hit]
                hp = s + tj[hit, None] * d[hit]
                rad = hp[:, :2] - c[j[hit], :2]
                rad /= np.linalg.norm(rad, axis=1, keepdims=True) + 1e-12
                normal[hit] = np.column_stack([rad, np.zeros(len(rad))])
                refl[hit] = p.cyl_refl[sel][j[hit]]
                cls[hit] = p.cyl_cls[sel][j[hit]]
                window[hit] = False

        # ellipsoids (tree crowns), porous: hits are jittered into the crown
        sel = _in_sector(*_ang_extent(p.ell[:, 0], p.ell[:, 1], p.ell[:, 3], s[0], s[1]), a0, a1)
        if sel.any():
            e = p.ell[sel]
            scale = np.stack([e[:, 3], e[:, 3], e[:, 4]], axis=1)  # (E,3)
            oc = (s - e[:, :3]) / scale  # (E,3)
            a = b = 0.0
            for k in range(3):  # per axis on (M, E) arrays
                ddk = d[:, k:k + 1] / scale[:, k]
                a = a + ddk * ddk
                b = b + 2 * ddk * oc[:, k]
            cc = (oc ** 2).sum(axis=1) - 1
            disc = b * b - 4 * a * cc
            sq = np.sqrt(np.maximum(disc, 0))
            te = (-b - sq) / (2 * a)
            tx = (-b + sq) / (2 * a)
            te = np.where((disc > 0) & (te > 0), te, np.inf)
            j = te.argmin(axis=1)
            tj = te[np.arange(M), j]
            hit = tj < best
            if hit.any():
                idx = np.flatnonzero(hit)
                depth = (tx[idx, j[idx]] - tj[idx]) * rng.uniform(0, e[j[idx], 5] * 0.5, idx.size)
                best[idx] = tj[idx] + depth
                hp = s + best[idx, None] * d[idx]
                nrm = (hp - e[j[idx], :3]) / scale[j[idx]]
                normal[idx] = nrm / (np.linalg.norm(nrm, axis=1, keepdims=True) + 1e-12)
                refl[idx] = p.ell_refl[sel][j[idx]] * rng.uniform(0.6, 1.3, idx.size)
                cls[idx] = p.ell_cls[sel][j[idx]]
                window[idx] = False

        return best, normal, refl, cls, window

    def sector(self, scan: int, k: int, t: float) -> dict[str, np.ndarray]:
        """Cast the rays of sector ``k`` of scan ``scan`` at scene time ``t`` (seconds).

        Returns positions (M,3) float64 in world coordinates (without ``origin``) and the
        per-point channels, for the rays that hit something within range."""
        o = self.o
        a_lo = k * self.n_az // o.chunks_per_scan
        a_hi = (k + 1) * self.n_az // o.chunks_per_scan
        az = (np.arange(a_lo, a_hi) + 0.5) * (2 * np.pi / self.n_az)
        A, Bm = az.size, o.beams
        # rays: azimuth-major, beams inner (the firing order of a real sensor)
        d = np.empty((A, Bm, 3))
        d[..., 0] = np.cos(az)[:, None] * self._cos_el[None, :]
        d[..., 1] = np.sin(az)[:, None] * self._cos_el[None, :]
        d[..., 2] = self._sin_el[None, :]
        d = d.reshape(-1, 3)
        beam = np.tile(np.arange(Bm, dtype=np.uint16), A)
        M = d.shape[0]
        s = self.sensor_at(t)
        rng = np.random.default_rng((o.seed, scan, k))
        # Cast in narrow azimuth blocks so each ray is tested only against nearby primitives.
        step = max(1, self.n_az // 64)
        parts = []
        for b0 in range(0, A, step):
            b1 = min(A, b0 + step)
            a0 = az[b0] - np.pi / self.n_az
            a1 = az[b1 - 1] + np.pi / self.n_az
            parts.append(self._cast(d[b0 * Bm:b1 * Bm], s, a0, a1, t, rng))
        best, normal, refl, cls, window = (np.concatenate(x) for x in zip(*parts))
        keep = (best >= o.min_range) & (best <= o.max_range)
        rng_m = best[keep]
        if o.range_noise > 0:
            rng_m = rng_m + rng.normal(0, o.range_noise, rng_m.size)
        dk = d[keep]
        pos = s + rng_m[:, None] * dk
        cls = cls[keep]
        refl = refl[keep]
        # ground materials from the position: asphalt roads with lane marks, grass verges
        g = cls == C_GROUND
        if g.any():
            gx, gy = np.abs(pos[g, 0]), np.abs(pos[g, 1])
            on_road = (gx < 6.0) | (gy < 6.0)
            mark = (((gx < 0.12) & (gy > 6) & (np.floor(pos[g, 1] / 3) % 2 == 0))
                    | ((gy < 0.12) & (gx > 6) & (np.floor(pos[g, 0] / 3) % 2 == 0))
                    | ((np.abs(gx - 5.8) < 0.1) & (gy > 6)) | ((np.abs(gy - 5.8) < 0.1) & (gx > 6)))
            grass = 0.3 + 0.08 * np.sin(pos[g, 0] * 0.7) * np.cos(pos[g, 1] * 0.5)
            refl[g] = np.where(mark, 0.95, np.where(on_road, 0.12, grass))
            cls[g] = np.where(on_road, C_ROAD, C_GROUND)
            pos[g, 2] += np.where(on_road, 0.0, 0.03 * np.sin(pos[g, 0] * 0.3) + 0.02)  # verge slightly raised
        w = window[keep]
        if w.any():  # window bands: dark glass every 3.2 m of height
            band = (pos[w, 2] % 3.2) > 1.1
            refl[w] = np.where(band, refl[w] * 0.35, refl[w])
        cos_inc = np.abs((normal[keep] * dk).sum(axis=1))
        falloff = 1.0 / (1.0 + (rng_m / (0.6 * o.max_range)) ** 2)
        # gamma 0.6 spreads the returns over the 0..255 range, like a sensor's calibrated output
        inten = 255.0 * (refl * (0.35 + 0.65 * cos_inc) * falloff) ** 0.6 + rng.normal(0, 2.0, rng_m.size)
        out = {
            "positions": pos,
            "intensity": np.clip(inten, 0, 255).astype(np.float32),
            "classification": cls,
            "beam": beam[keep],
            "range": rng_m.astype(np.float32),
        }
        self.counters["rays"] += M
        self.counters["returns"] += int(keep.sum())
        return out

    # ------------------------------------------------------------------ Transport API
    def open(self) -> None:
        self._t0 = time.monotonic()

    def make_chunk(self, scan: int, k: int) -> PointChunk:
        """The chunk of sector ``k`` of scan ``scan`` (deterministic; no pacing)."""
        o = self.o
        if o.cache_scans:
            key = (scan % o.cache_scans, k)
            c = self._cache.get(key)
            if c is None:
                c = self._cache[key] = self._make_chunk(*key)
            return PointChunk(positions=c.positions, channels=c.channels, source_id=self.source_id,
                              seq=scan * o.chunks_per_scan + k)
        return self._make_chunk(scan, k)

    # ------------------------------------------------------------------ moving mode
    EPOCH_NS = 1_700_000_000 * 1_000_000_000  # stamps: this + scene time
    TF_PERIOD_NS = 50_000_000

    def base_pose(self, t: float) -> tuple[np.ndarray, float]:
        """odom <- base_link at scene time ``t``: (translation, yaw)."""
        s = self.sensor_at(t)
        return np.array([s[0], s[1], 0.0]) + self.origin, 0.15 * math.sin(0.8 * t)

    def transforms_until(self, t: float) -> Optional[Transforms]:
        """The 20 Hz ``odom -> base_link`` samples not yet sent up to one period past ``t``
        (so the cloud at ``t`` is bracketed), the static mount first."""
        out = []
        if getattr(self, "_tf_next", None) is None:
            self._tf_next = 0
            out.append(Transform("base_link", "lidar", 0, (0.0, 0.0, self.o.sensor_height), (0.0, 0.0, 0.0, 1.0), True))
        end = int(t * 1e9) + self.TF_PERIOD_NS
        while self._tf_next <= end:
            ts = self._tf_next
            tr, yaw = self.base_pose(ts / 1e9)
            out.append(Transform("odom", "base_link", self.EPOCH_NS + ts, tuple(tr),
                                 (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))))
            self._tf_next += self.TF_PERIOD_NS
        return Transforms(out, self.source_id) if out else None

    def _to_sensor(self, pos: np.ndarray, t: float) -> np.ndarray:
        tr, yaw = self.base_pose(t)
        c, s_ = math.cos(yaw), math.sin(yaw)
        rel = pos + self.origin - tr
        out = np.empty_like(rel)
        out[:, 0] = c * rel[:, 0] + s_ * rel[:, 1]  # Rz(yaw)^T
        out[:, 1] = -s_ * rel[:, 0] + c * rel[:, 1]
        out[:, 2] = rel[:, 2] - self.o.sensor_height
        return out

    def _make_chunk(self, scan: int, k: int) -> PointChunk:
        o = self.o
        t = (scan + (k + 1) / o.chunks_per_scan) / o.scan_hz
        sec = self.sector(scan, k, t)
        if o.mode == "moving":
            pos = self._to_sensor(sec["positions"], t)
            if o.positions_dtype == "float32":
                pos = pos.astype(np.float32)
            return PointChunk(positions=pos, channels={c: sec[c] for c in o.channels}, source_id=self.source_id,
                              seq=scan * o.chunks_per_scan + k, stamp_ns=self.EPOCH_NS + int(round(t * 1e9)),
                              frame_id="lidar")
        pos = sec["positions"] + self.origin
        if o.positions_dtype == "float32":
            pos = pos.astype(np.float32)
        chans = {c: sec[c] for c in o.channels}
        return PointChunk(positions=pos, channels=chans, source_id=self.source_id,
                          seq=scan * o.chunks_per_scan + k)

    def chunks(self) -> Iterator[Optional[PointChunk]]:
        o = self.o
        t0 = getattr(self, "_t0", None) or time.monotonic()
        scan = 0
        while o.scans == 0 or scan < o.scans:
            for k in range(o.chunks_per_scan):
                if o.realtime:
                    due = t0 + (scan + (k + 1) / o.chunks_per_scan) / (o.scan_hz * o.rate)
                    while True:
                        left = due - time.monotonic()
                        if left <= 0:
                            break
                        time.sleep(min(left, 0.05))
                        if left > 0.05:
                            yield None
                if o.mode == "moving":
                    tfs = self.transforms_until((scan + (k + 1) / o.chunks_per_scan) / o.scan_hz)
                    if tfs is not None:
                        yield tfs
                yield self.make_chunk(scan, k)
            scan += 1
            self.counters["scans"] = scan
