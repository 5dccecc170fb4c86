"""The scenes the render benchmarks draw: the tiers' scenes (bench_tiers.py,
bench_edl_cpu_gl.py, quads_agreement.py) and the tiled cloud of the wgpu frame-time runs
(bench_render.py, ab_raster.py)."""
from __future__ import annotations

import time
from typing import Optional

import numpy as np

from pointflow.render.base import FrameInput
from pointflow.render.camera import Camera

from . import DATA

W, H = 1280, 720


# ----------------------------------------------------------------------------- scenes
def _frame(world: np.ndarray, intensity: np.ndarray, *, origin=None, t_ms=None, rgb=None,
           importance=None) -> FrameInput:
    """A full ring (capacity = n) in logical order; positions float32 offsets from origin."""
    n = world.shape[0]
    org = np.floor(world.min(axis=0)) if origin is None else np.asarray(origin, np.float64)
    inten = np.asarray(intensity, np.float32)
    t = np.linspace(0.0, 10_000.0, n) if t_ms is None else np.asarray(t_ms, np.float64)
    ch = {"intensity": inten}
    if rgb is not None:
        ch["rgb"] = rgb
    lo, hi = float(np.nanmin(inten)), float(np.nanmax(inten))
    imp = inten if importance is None else np.asarray(importance, np.float32)
    return FrameInput(positions=(world - org).astype(np.float32), importance=imp, t_ingest_ms=t, channels=ch,
                      head=0, size=n, capacity=n, origin=org, now_ms=float(t.max()),
                      channel_ranges={"intensity": (lo, hi), "importance": (float(imp.min()), float(imp.max()))})


def _fit(world: np.ndarray, aspect: float, **kw) -> Camera:
    lo, hi = np.percentile(world, 1, axis=0), np.percentile(world, 99, axis=0)
    return Camera.fit(lo, hi, aspect=aspect, **kw)


def scene_demo(aspect: float, n_target: int) -> tuple[FrameInput, Camera, str]:
    """The demo: the synthetic town swept by the simulated lidar (as configs/demo.yaml)."""
    from pointflow.ingest.transports.synthetic import SyntheticTransport

    opts = SyntheticTransport.validate_options({"realtime": False, "points_per_scan": 100_000,
                                                "scans": max(1, n_target // 100_000)}, "bench")
    tr = SyntheticTransport(opts, "bench")
    tr.open()
    pos, inten = [], []
    for ch in tr.chunks():
        if ch is None:
            continue
        pos.append(np.asarray(ch.positions, np.float64))
        inten.append(np.asarray(ch.channels["intensity"], np.float32))
    tr.close()
    world, it = np.concatenate(pos), np.concatenate(inten)
    # ingest time: scans arrive at 10 Hz, in order
    t = np.linspace(0, 100.0 * len(pos) / 10, len(world))
    return _frame(world, it, t_ms=t), _fit(world, aspect, elevation_deg=30), f"synthetic town, {len(world):,} pts"


def scene_dense(aspect: float, n: int) -> tuple[FrameInput, Camera, str]:
    """A dense static scan: rolling terrain with buildings, evenly sampled."""
    rng = np.random.default_rng(0)
    xy = rng.uniform(-60, 60, (n, 2))
    z = 2.5 * np.sin(xy[:, 0] / 9) * np.cos(xy[:, 1] / 11)
    for cx, cy, h in ((10, -5, 9), (-25, 20, 14), (30, 30, 6), (-20, -30, 11)):
        m = (np.abs(xy[:, 0] - cx) < 7) & (np.abs(xy[:, 1] - cy) < 7)
        z[m] += h
    world = np.column_stack([xy, z])
    inten = ((z - z.min()) / (np.ptp(z) + 1e-9)).astype(np.float32)
    return _frame(world, inten), _fit(world, aspect), f"dense static scan, {n:,} pts"


def scene_autzen(aspect: float) -> Optional[tuple[FrameInput, Camera, str]]:
    path = DATA / "autzen_trim.laz"
    if not path.exists():
        return None
    import laspy

    las = laspy.read(str(path))
    world = np.column_stack([las.x, las.y, las.z]).astype(np.float64)
    inten = np.asarray(las.intensity, np.float32)
    return _frame(world, inten), _fit(world, aspect, elevation_deg=45), f"autzen_trim.laz (georeferenced), {len(world):,} pts"


def scene_ouster(aspect: float) -> Optional[tuple[FrameInput, Camera, str]]:
    files = sorted((DATA / "ouster_os1_128").glob("*.npz"))
    if not files:
        return None
    pos, refl = [], []
    for f in files:
        d = np.load(f)
        pos.append(d["xyz"].astype(np.float64))
        refl.append(d["reflectivity"].astype(np.float32))
    world, inten = np.concatenate(pos), np.concatenate(refl)
    ok = np.isfinite(world).all(axis=1) & (np.abs(world) < 80).all(axis=1)
    world, inten = world[ok], inten[ok]
    t = np.repeat(np.arange(len(files)) * 100.0, [int(o.sum()) for o in np.split(ok, np.cumsum([len(p) for p in pos])[:-1])])
    cam = Camera(eye=[-25, -18, 14], target=[5, 0, 0], near=0.5, far=200, fov_deg=60)
    return _frame(world, inten, t_ms=t), cam, f"Ouster OS1-128, {len(files)} scans, {len(world):,} pts"


# ----------------------------------------------------------------------------- the tiled cloud (bench_render)
def base_cloud() -> tuple[np.ndarray, np.ndarray, str]:
    """(world xyz float64, intensity float32, name)."""
    laz = DATA / "autzen_trim.laz"
    if laz.exists():
        try:
            import laspy
            las = laspy.read(str(laz))
            xyz = np.column_stack([las.x, las.y, las.z]).astype(np.float64)
            return xyz, np.asarray(las.intensity, np.float32), "autzen_trim.laz (tiled)"
        except Exception as e:  # pragma: no cover - data/laspy problems fall back
            print(f"could not read {laz}: {e}; using a synthetic terrain")
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 1000, size=(110_000, 2))
    z = 20 * np.sin(xy[:, 0] / 90) * np.cos(xy[:, 1] / 120) + rng.normal(0, 0.5, len(xy))
    return np.column_stack([xy, z]), (z - z.min()).astype(np.float32), "synthetic terrain"


def tiled(base: np.ndarray, inten: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n points: copies of the base cloud on a square grid of tiles (each tile jittered)."""
    m = len(base)
    k = int(np.ceil(n / m))
    side = int(np.ceil(np.sqrt(k)))
    ext = base.max(0) - base.min(0)
    reps = np.arange(k)
    shift = np.column_stack([(reps % side) * ext[0], (reps // side) * ext[1], np.zeros(k)])
    idx = np.arange(n)
    pts = base[idx % m] + shift[idx // m]
    return pts, inten[idx % m]


def make_frame(world: np.ndarray, inten: np.ndarray) -> FrameInput:
    n = len(world)
    org = np.floor(world.min(0))
    lo, hi = float(inten.min()), float(inten.max())
    return FrameInput(positions=(world - org).astype(np.float32), importance=inten.copy(),
                      t_ingest_ms=np.zeros(n), channels={"intensity": inten.copy()}, head=0, size=n, capacity=n,
                      origin=org, now_ms=0.0, channel_ranges={"intensity": (lo, hi), "importance": (lo, hi)})


def camera_for(world: np.ndarray) -> Camera:
    lo, hi = world.min(0), world.max(0)
    return Camera.fit(lo, hi, aspect=W / H)


def rewritten_frames(r, f: FrameInput, cam: Camera, frames: int, head: int = 0) -> tuple[list[float], list, int]:
    """The frame-time runs' steady state: ``frames`` frames of renderer ``r``, each with the
    next 1% of the ring marked rewritten (a dirty range) and its image read back
    (``read_image``). Returns (wall ms per frame, FrameStats per frame, the next head)."""
    n = int(f.capacity)
    step = max(n // 100, 1)
    ts, stats = [], []
    for _ in range(frames):
        f.dirty = [(head, min(head + step, n))]
        head = (head + step) % n
        t0 = time.perf_counter()
        stats.append(r.render(f, cam))
        r.read_image()
        ts.append((time.perf_counter() - t0) * 1e3)
    return ts, stats, head


def streamed_frames(r, f: FrameInput, cam: Camera, frames: int, head: int = 0) -> tuple[float, int]:
    """A live view's frames: ``frames`` frames of ``r`` back to back, each with the next 1% of
    the ring rewritten, no readback between them (the tier's own wait bounds the frames in
    flight), ``finish()`` after the last. Returns (wall ms per frame, the next head)."""
    n = int(f.capacity)
    step = max(n // 100, 1)
    t0 = time.perf_counter()
    for _ in range(frames):
        f.dirty = [(head, min(head + step, n))]
        head = (head + step) % n
        r.render(f, cam)
    fin = getattr(r, "finish", None)
    if fin is not None:
        fin()
    return (time.perf_counter() - t0) * 1e3 / max(frames, 1), head


def tiled_frame(n: int) -> tuple[FrameInput, np.ndarray, str]:
    """The base cloud tiled to n points as a full ring (:func:`tiled`, :func:`make_frame`), with
    its float64 world coordinates (to place cameras) and the scene's name."""
    base, inten0, name = base_cloud()
    world, inten = tiled(base, inten0, n)
    return make_frame(world, inten), world, name


def tiled_scene(n: int) -> tuple[FrameInput, Camera]:
    """The frame-time runs' scene at n points: the base cloud tiled (:func:`tiled`), as a
    full ring (:func:`make_frame`), with the camera that frames it."""
    base, inten0, _ = base_cloud()
    world, inten = tiled(base, inten0, n)
    return make_frame(world, inten), camera_for(world)
