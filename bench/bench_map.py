"""The map layer in a whole pipeline (issue 30's performance targets), on real data.

Map: ``autzen_trim.laz`` (airborne LiDAR, 110,000 points, ../shared/data) laid out as a
``--tiles`` x ``--tiles`` mosaic of shifted copies written by laspy into one LAZ (real
points, a bigger file; 3.96 M points at 6 x 6), its level-of-detail index built before the
timed runs. Live: an Ouster OS-1-128 scan replayed at 10 Hz above the map. Measured:

* ``first_picture_s`` — from ``Pipeline.start()`` being called to the first frame the render
  stage drew with map points (its stats polled every 20 ms; also from start() returning);
  target <= 2 s with the index built;
* ``refine_s`` — a camera move (``Pipeline.camera``) to the map stage having loaded every
  node the new view wants and the render stage holding that version (``map_refine_ms`` is
  the map stage's own measure from the camera message); target <= 1 s;
* ``frame_ms`` — the render stage's frame time with a map budget of B points drawn vs a
  ring of B live points (same tier, same size, the camera orbiting so every frame is drawn),
  runs interleaved A B A B, medians; target map <= 1.2 x ring;
* ``rss`` — the map stage's RSS while the camera flies over the map with ``cache_mb``
  small against the file (the region of ``point_budget`` slots and the interpreter are the
  stated overhead: RSS before any node is loaded).

The machine is shared with other engineers (2 cores): ``uptime`` is written before and after.

    PYTHONPATH=$PWD .venv/bin/python bench/bench_map.py             # ~10 min on 2 cores
    PYTHONPATH=$PWD .venv/bin/python bench/bench_map.py --tiles 2 --budget 200000 --only-inprocess  # quicker

Writes ``bench/results/map.json``.
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
import time

import numpy as np

import _harness as H
from pointflow import Pipeline

RESULTS = H.RESULTS
DATA = H.DATA


def mosaic(tiles: int, out: str) -> tuple[str, np.ndarray, np.ndarray]:
    """autzen_trim as a tiles x tiles mosaic in one LAZ (laspy); its bounds."""
    import laspy

    src = laspy.read(str(DATA / "autzen_trim.laz"))
    x, y, z = (np.asarray(a, np.float64) for a in (src.x, src.y, src.z))
    w, h = x.max() - x.min() + 1.0, y.max() - y.min() + 1.0
    hdr = laspy.LasHeader(point_format=src.header.point_format, version=src.header.version)
    hdr.scales, hdr.offsets = src.header.scales, src.header.offsets
    with laspy.open(out, mode="w", header=hdr) as wr:
        for i in range(tiles):
            for j in range(tiles):
                rec = laspy.ScaleAwarePointRecord.zeros(len(x), header=hdr)
                for name in src.point_format.dimension_names:
                    rec[name] = src[name]
                rec.x, rec.y, rec.z = x + i * w, y + j * h, z
                wr.write_points(rec)
    lo = np.array([x.min(), y.min(), z.min()])
    hi = np.array([x.min() + tiles * w, y.min() + tiles * h, z.max()])
    return out, lo, hi


def live_scan(out_dir: str, centre: np.ndarray) -> str:
    """An Ouster scan (8 beams, ~6,100 points), shifted to float above the map's middle (a
    sensor over the map): the live part stays small, so the frame-time comparison is the
    map's B points against a ring's B points."""
    scans = sorted((DATA / "ouster_osf_8beam").glob("*.npz"))
    d = np.load(scans[0])
    xyz = np.asarray(d["xyz"], np.float64) / 0.3048 + centre + [0, 0, 150.0]  # metres -> feet, like autzen
    f = os.path.join(out_dir, "scan.npz")
    np.savez(f, x=xyz[:, 0], y=xyz[:, 1], z=xyz[:, 2])
    return f


def config(map_path: str, live: str, budget: int, cache_mb: float, cache_dir: str, *, orbit: float = 0.0,
           size=(960, 540)) -> dict:
    return {"source": {"transport": "file", "name": "lidar", "options": {"path": live, "realtime": True,
                                                                          "loop": True}},
            "ring": {"max_points": 20_000},
            "render": {"size": list(size), "color_by": "z", "output": {"every_n_frames": 1_000_000},
                       "camera": {"orbit_deg_per_s": orbit}},
            "map": {"path": map_path, "point_budget": budget, "cache_mb": cache_mb, "cache_dir": cache_dir}}


def _poll(pipe, until, timeout: float, dt: float = 0.02):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        st = pipe.stats()
        if until(st):
            return st
        time.sleep(dt)
    return None


def first_picture_and_refine(map_path, live, lo, hi, cache_dir, budget: int) -> dict:
    cfg = config(map_path, live, budget, 256.0, cache_dir)
    t0 = time.monotonic()
    pipe = Pipeline.from_dict(cfg, out_dir=tempfile.mkdtemp(prefix="bench-map-"))
    pipe.start()
    t_started = time.monotonic()
    out: dict = {}
    try:
        drew = lambda st: (st["stages"]["render"].get("map_points") or 0) > 0 and \
            (st["stages"]["render"].get("frames") or 0) > 0  # noqa: E731
        st = _poll(pipe, drew, 60)
        t1 = time.monotonic()
        out["first_picture_s"] = round(t1 - t0, 3) if st else None
        out["first_picture_after_started_s"] = round(t1 - t_started, 3) if st else None
        out["start_returned_s"] = round(t_started - t0, 3)
        out["map_open_s"] = st["stages"]["map"].get("map_open_s") if st else None
        _poll(pipe, lambda s: s["stages"]["map"].get("map_refine_ms") is not None, 60)
        moves = []
        c = (lo + hi) / 2
        span = float(np.max(hi - lo))
        views = [(c + [0.3 * span, -0.3 * span, 0.15 * span], c + [0.3 * span, 0, 0]),
                 (c + [-0.35 * span, 0.2 * span, 0.1 * span], c + [-0.2 * span, 0.35 * span, 0]),
                 (c + [0.0, 0.0, 0.6 * span], c)]
        for eye, target in views:
            moves0 = pipe.stats()["stages"]["map"].get("map_camera_moves", 0)
            ta = time.monotonic()
            pipe.camera(eye=[float(v) for v in eye], target=[float(v) for v in target], up=[0, 0, 1])
            done = lambda s: (s["stages"]["map"].get("map_camera_moves", 0) != moves0  # noqa: E731
                              and s["stages"]["map"].get("map_refine_ms") is not None
                              and s["stages"]["map"].get("map_version") == s["stages"]["render"].get("map_version"))
            s = _poll(pipe, done, 30)
            tb = time.monotonic()
            moves.append({"refine_s": round(tb - ta, 3) if s else None,
                          "map_refine_ms": s["stages"]["map"].get("map_refine_ms") if s else None,
                          "map_points": s["stages"]["render"].get("map_points") if s else None,
                          "nodes": s["stages"]["map"].get("map_nodes") if s else None})
        out["moves"] = moves
        out["refine_s_max"] = max((m["refine_s"] or 1e9) for m in moves)
        out["tier"] = pipe.stats()["stages"]["render"].get("tier")
    finally:
        pipe.stop()
    return out


def frame_times(map_path, live_b: str, live, cache_dir, budget: int, seconds: float, repeats: int) -> dict:
    """The render stage's frame time: a map of B points vs B points in the ring, both runs with
    the same live scan streaming, the camera orbiting (every frame drawn); runs interleaved."""
    runs: dict[str, list] = {"map": [], "ring": []}
    tiers = {}
    for _ in range(repeats):
        for kind in ("map", "ring"):
            if kind == "map":
                cfg = config(map_path, live, budget, 256.0, cache_dir, orbit=20.0)
            else:  # the same live scan, and B more points in the ring instead of the map
                cfg = config(map_path, live, budget, 256.0, cache_dir, orbit=20.0)
                cfg.pop("map")
                cfg["ring"]["max_points"] = budget + 20_000
                cfg["sources"] = [cfg.pop("source"), {"transport": "file", "name": "ring_b", "options": {
                    "path": live_b, "realtime": False, "loop": False}}]
            with Pipeline.from_dict(cfg, out_dir=tempfile.mkdtemp(prefix="bench-map-")) as pipe:
                key = "map_points" if kind == "map" else "drawn_count"  # points in the ring when drawn
                ready = _poll(pipe, lambda s: (s["stages"]["render"].get(key) or 0) >= 0.95 * budget, 120)
                if ready is None:
                    runs[kind].append(None)
                    continue
                if kind == "map":  # wait until the map stage settled
                    _poll(pipe, lambda s: s["stages"]["map"].get("map_refine_ms") is not None, 60)
                samples, drawn, f0, cpu, v0 = [], [], None, [], None
                end = time.monotonic() + seconds
                while time.monotonic() < end:
                    st = pipe.stats()["stages"]
                    r = st["render"]
                    if f0 is None:
                        f0 = r.get("frames", 0)
                    if kind == "map":  # the map stage's work while the camera orbits
                        m = st.get("map") or {}
                        cpu.append(m.get("cpu_percent"))
                        v0 = (m.get("map_versions", 0), m.get("map_nodes_loaded", 0)) if v0 is None else v0
                    samples.append(r.get("last_frame_ms"))
                    drawn.append(r.get("map_points") if kind == "map" else r.get("drawn_count"))
                    time.sleep(0.1)
                st = pipe.stats()["stages"]
                r = st["render"]
                tiers[kind] = r.get("tier")
                runs[kind].append({"median_ms": float(np.median([s for s in samples if s])),
                                   "frames": r.get("frames", 0) - f0, "points": int(np.median(drawn))})
                if kind == "map":
                    m = st.get("map") or {}
                    cpu = [c for c in cpu if c is not None]
                    runs[kind][-1].update(map_cpu_percent_median=float(np.median(cpu)) if cpu else None,
                                          map_versions=m.get("map_versions", 0) - v0[0],
                                          map_nodes_loaded=m.get("map_nodes_loaded", 0) - v0[1])
    med = {k: float(np.median([r["median_ms"] for r in v if r])) if any(v) else None for k, v in runs.items()}
    return {"budget": budget, "runs": runs, "median_ms": med, "tiers": tiers,
            "ratio_map_over_ring": round(med["map"] / med["ring"], 3) if med["map"] and med["ring"] else None}


def frame_times_inprocess(map_path, cache_dir, budget: int, frames: int, backend: str, tmp: str) -> dict:
    """The same comparison in one process, frame by frame interleaved (A B A B ...), so the
    machine's load swings hit both alike: the render stage's map layer composing a live scan
    (its slots dirty every frame) with B map points, drawn by the tier, against one ring
    holding the same B points and the live scan (only the live slots dirty). Same tier class,
    same size, same camera; medians."""
    import logging
    import types

    import zmq

    from pointflow.config import EndpointsConfig, RenderConfig
    from pointflow.map import open_map, select_nodes
    from pointflow.render import mapregion as mr
    from pointflow.render.base import FrameInput
    from pointflow.render.camera import Camera
    from pointflow.render.maplayer import MapLayer
    from pointflow.render.select import select_renderer

    src = open_map(map_path, cache_dir=cache_dir, progress=False)
    lo, hi = src.bounds
    cam = Camera.fit(lo, hi, aspect=16 / 9)
    keys = select_nodes(src, cam.view_proj(960, 540), (960, 540), cam.eye, budget)
    pts = np.concatenate([src.load(k)["positions"] for k in keys])
    src.close()
    scan = np.load(sorted((DATA / "ouster_osf_8beam").glob("*.npz"))[0])["xyz"].astype(np.float64) / 0.3048
    live = scan + (lo + hi) / 2 + [0, 0, 150.0]
    L, B = live.shape[0], pts.shape[0]
    origin = np.round((lo + hi) / 2, 3)
    ep = EndpointsConfig(map=f"ipc://{tmp}/bm.sock", map_camera=f"ipc://{tmp}/bmc.sock")
    zctx = zmq.Context.instance()
    cfg = types.SimpleNamespace(map=types.SimpleNamespace(point_budget=budget), sources=[types.SimpleNamespace(name="l")])
    layer = MapLayer(cfg, types.SimpleNamespace(zmq=zctx, endpoints=ep, log=logging.getLogger("bench")), 20_000)
    reg = mr.MapRegion.create(tmp, budget, [])
    reg.positions[:B] = pts
    push = zctx.socket(zmq.PUSH)
    push.connect(ep.map)
    push.send(mr.encode({"type": "version", "version": 1, "full": True, "region": reg.path, "slots": budget,
                         "channels": [], "files": [map_path], "origin": list(origin), "set": [[0, B]], "cleared": [],
                         "points": B, "nodes": len(keys), "channel_ranges": {}}))
    while layer.version < 1:
        layer.poll()
        time.sleep(0.01)

    def ring_frame(cap: int, world: np.ndarray, dirty) -> FrameInput:
        pos = np.full((cap, 3), np.nan, np.float32)
        pos[:world.shape[0]] = (world - origin).astype(np.float32)
        return FrameInput(positions=pos, importance=np.ones(cap, np.float32), t_ingest_ms=np.zeros(cap), channels={},
                          head=0, size=world.shape[0], capacity=cap, origin=origin, now_ms=0.0, dirty=dirty)

    be, _, raster = backend.partition(":")  # "cpu:compute" = the cpu tier's compiled raster
    rc = RenderConfig(backend=be, raster=raster or "auto", size=(960, 540), color_by="z")
    a, _ = select_renderer(rc, layer.capacity, [])
    b = type(a)(a.cfg, B + L, [])
    live_frame = ring_frame(20_000, live, None)
    both = ring_frame(B + L, np.concatenate([live, pts]), None)
    ta, tb = [], []
    for i in range(frames + 2):  # two warm-up frames each (full uploads), then only the live slots change
        t0 = time.perf_counter()
        f = layer.compose(live_frame)
        a.render(f, cam)
        layer.drawn()
        if hasattr(a, "finish"):
            a.finish()
        t1 = time.perf_counter()
        b.render(both, cam)
        if hasattr(b, "finish"):
            b.finish()
        t2 = time.perf_counter()
        live_frame.dirty, both.dirty = [(0, L)], [(0, L)]
        if i >= 2:
            ta.append((t1 - t0) * 1e3)
            tb.append((t2 - t1) * 1e3)
    tier = a.info().get("tier")
    info = a.info()
    a.close()
    b.close()
    layer.close()
    push.close(0)
    reg.close()
    ma, mb = float(np.median(ta)), float(np.median(tb))
    return {"backend": backend, "tier": tier, "tier_info": str(info)[:200], "map_points": B, "live_points": L, "frames": frames,
            "map_ms_median": round(ma, 3), "ring_ms_median": round(mb, 3), "ratio_map_over_ring": round(ma / mb, 3),
            "map_ms": [round(x, 2) for x in ta], "ring_ms": [round(x, 2) for x in tb]}


def error_vs_budget(map_path, cache_dir, budgets: list, frames: int, out_png: str) -> dict:
    """Image error and frame time against the point budget, on the real map: the nodes
    select_nodes gives for a view low over the mosaic (as the map stage chooses them), drawn
    by the cpu tier's compiled raster; error = share of pixels that differ from drawing every
    point of the file; frame time = median over ``frames`` frames. Writes a chart."""
    from pointflow.config import RenderConfig
    from pointflow.map import open_map, select_nodes
    from pointflow.render.base import FrameInput
    from pointflow.render.camera import Camera
    from pointflow.render.select import select_renderer

    src = open_map(map_path, cache_dir=cache_dir, progress=False)
    lo, hi = src.bounds
    c = (lo + hi) / 2
    span = float(np.max(hi - lo))
    cam = Camera(eye=c + [0.0, -0.55 * span, 0.25 * span], target=c + [0, 0.05 * span, 0], up=[0, 0, 1],
                 near=span * 1e-3, far=span * 3)
    w, h = 960, 540
    origin = np.round(c, 3)
    rc = RenderConfig(backend="cpu", raster="compute", size=(w, h), color_by="z")

    def draw(pts: np.ndarray):
        n = pts.shape[0]
        r, _ = select_renderer(rc, n, [])
        f = FrameInput(positions=(pts - origin).astype(np.float32), importance=np.ones(n, np.float32),
                       t_ingest_ms=np.zeros(n), channels={}, head=0, size=n, capacity=n, origin=origin,
                       now_ms=0.0, dirty=None, channel_ranges={})
        r.render(f, cam)
        times = []
        for _ in range(frames):
            f.dirty = []
            t0 = time.perf_counter()
            r.render(f, cam)
            times.append((time.perf_counter() - t0) * 1e3)
        img = r.read_image()
        r.close()
        return img, float(np.median(times))

    every = np.concatenate([src.load(k)["positions"] for k in src.keys()])
    full, full_ms = draw(every)
    rows = []
    for b in budgets:
        keys = select_nodes(src, cam.view_proj(w, h), (w, h), cam.eye, b)
        pts = np.concatenate([src.load(k)["positions"] for k in keys]) if keys else np.zeros((0, 3))
        img, ms = draw(pts) if len(pts) else (np.zeros_like(full), 0.0)
        rows.append({"budget": b, "points": int(len(pts)), "nodes": len(keys),
                     "pixels_differing": round(float((img != full).any(axis=-1).mean()), 4), "frame_ms": round(ms, 2)})
        print("budget", rows[-1], flush=True)
    src.close()
    plt = H.pyplot()
    if plt is not None:
        fig, ax = plt.subplots(figsize=(7, 4))
        xs = [r["points"] for r in rows]
        ax.plot(xs, [100 * r["pixels_differing"] for r in rows], "o-", color="C0")
        ax.set_xscale("log")
        ax.set_xlabel("map points drawn (point budget)")
        ax.set_ylabel("pixels differing from every point (%)", color="C0")
        ax2 = ax.twinx()
        ax2.plot(xs, [r["frame_ms"] for r in rows], "s--", color="C1")
        ax2.axhline(full_ms, color="C1", lw=0.8, ls=":")
        ax2.set_ylabel("frame time, cpu compiled raster (ms)", color="C1")
        ax.set_title(f"{os.path.basename(map_path)} ({len(every):,} points): error and frame time by budget",
                     fontsize=9)
        fig.tight_layout()
        fig.savefig(out_png, dpi=110)
    return {"all_points": int(len(every)), "all_frame_ms": round(full_ms, 2), "rows": rows, "chart": out_png}


def ring_points(n: int, lo, hi, out_dir: str) -> str:
    """B live points over the same area (a file replayed at once: the ring of B points)."""
    import laspy

    las = laspy.read(str(DATA / "autzen_trim.laz"))
    xyz = np.column_stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)])
    reps = int(np.ceil(n / len(xyz)))
    rng = np.random.default_rng(0)
    pts = np.concatenate([xyz + [rng.uniform(0, hi[0] - lo[0] - 1200), rng.uniform(0, hi[1] - lo[1] - 600), 0]
                          for _ in range(reps)])[:n]
    f = os.path.join(out_dir, "ring_b.npz")
    np.savez(f, x=pts[:, 0], y=pts[:, 1], z=pts[:, 2])
    return f


def rss_flight(map_path, live, lo, hi, cache_dir, budget: int, cache_mb: float) -> dict:
    """Fly the camera over the map with a small cache: the map stage's RSS stays near
    cache_mb + its overhead (RSS before the first node was read)."""
    cfg = config(map_path, live, budget, cache_mb, cache_dir)
    samples = []
    with Pipeline.from_dict(cfg, out_dir=tempfile.mkdtemp(prefix="bench-map-")) as pipe:
        first = _poll(pipe, lambda s: s["stages"]["map"].get("rss_bytes"), 30, dt=0.005)
        base = first["stages"]["map"]["rss_bytes"] if first else None
        base_loads = first["stages"]["map"].get("map_nodes_loaded") if first else None
        c = (lo + hi) / 2
        span = hi - lo
        for k in range(24):
            a = 2 * np.pi * k / 24
            p = c + [0.4 * span[0] * np.cos(a), 0.4 * span[1] * np.sin(a), 0]
            pipe.camera(eye=[float(v) for v in p + [0, -200, 250]], target=[float(v) for v in p], up=[0, 0, 1])
            time.sleep(0.6)
            m = pipe.stats()["stages"]["map"]
            samples.append({"rss_mb": round(m["rss_bytes"] / 2**20, 1),
                            "cache_mb_used": round((m.get("map_cache_bytes") or 0) / 2**20, 1),
                            "loads": m.get("map_nodes_loaded"), "points_read": m.get("points_in")})
    region_mb = budget * (24 + 2) / 2**20  # positions float64, file index (colour by z: no channel kept)
    rss = [s["rss_mb"] for s in samples]
    return {"cache_mb": cache_mb, "budget": budget, "rss_first_mb": round(base / 2**20, 1) if base else None,
            "nodes_loaded_at_first": base_loads,
            "region_mb": round(region_mb, 1), "rss_peak_mb": max(rss), "rss_last_mb": rss[-1],
            "points_read": samples[-1]["points_read"], "samples": samples}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tiles", type=int, default=6)
    ap.add_argument("--budget", type=int, default=500_000)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--frames", type=int, default=15, help="frames per side of the in-process comparison")
    ap.add_argument("--backends", default="cpu:compute,wgpu",
                    help="tiers of the in-process comparison (backend[:raster])")
    ap.add_argument("--only-inprocess", action="store_true")
    ap.add_argument("--only-error", action="store_true", help="only image error and frame time by budget")
    ap.add_argument("--only-pipeline", action="store_true",
                    help="only the whole pipelines: first picture, refine, frame time while orbiting")
    ap.add_argument("--out", default=str(RESULTS / "map.json"))
    a = ap.parse_args()
    tmp = tempfile.mkdtemp(prefix="bench-map-")
    res: dict = {"machine": H.machine(command=H.command()), "args": vars(a)}
    t = time.monotonic()
    path, lo, hi = mosaic(a.tiles, os.path.join(tmp, f"autzen_{a.tiles}x{a.tiles}.laz"))
    res["map"] = {"file": os.path.basename(path), "points": 110_000 * a.tiles ** 2,
                  "bytes": os.path.getsize(path), "write_s": round(time.monotonic() - t, 2)}
    cache_dir = os.path.join(tmp, "index")
    from pointflow.map import open_map

    t = time.monotonic()
    open_map(path, cache_dir=cache_dir, progress=False).close()
    res["map"]["index_build_s"] = round(time.monotonic() - t, 2)
    print("index built:", res["map"], flush=True)
    live = live_scan(tmp, (lo + hi) / 2)
    budgets = [25_000, 50_000, 100_000, 200_000, 400_000, 1_000_000, 2_000_000]
    if a.only_error:
        res["error_vs_budget"] = error_vs_budget(path, cache_dir, budgets, a.frames, str(RESULTS / "map_budget.png"))
        H.write_result(a.out, {**res, "machine": H.machine_done(res["machine"])})
        return
    if a.only_inprocess:
        res["frame_time_inprocess"] = [frame_times_inprocess(path, cache_dir, a.budget, a.frames, be, tmp)
                                       for be in a.backends.split(",")]
        for r in res["frame_time_inprocess"]:
            print("frame time in process:", {k: v for k, v in r.items() if k not in ("map_ms", "ring_ms")})
        H.write_result(a.out, {**res, "machine": H.machine_done(res["machine"])})
        return
    res["first_picture"] = first_picture_and_refine(path, live, lo, hi, cache_dir, a.budget)
    print("first picture / refine:", json.dumps(res["first_picture"]), flush=True)
    if not a.only_pipeline:
        res["frame_time_inprocess"] = [frame_times_inprocess(path, cache_dir, a.budget, a.frames, be, tmp)
                                       for be in a.backends.split(",")]
        for r in res["frame_time_inprocess"]:
            print("frame time in process:", {k: v for k, v in r.items() if k not in ("map_ms", "ring_ms")},
                  flush=True)
    live_b = ring_points(a.budget, lo, hi, tmp)
    res["frame_time"] = frame_times(path, live_b, live, cache_dir, a.budget, a.seconds, a.repeats)
    print("frame time:", json.dumps(res["frame_time"]["median_ms"]), res["frame_time"]["ratio_map_over_ring"],
          flush=True)
    if not a.only_pipeline:
        res["rss"] = rss_flight(path, live, lo, hi, cache_dir, a.budget, 16.0)
        print("rss:", {k: v for k, v in res["rss"].items() if k != "samples"}, flush=True)
    H.machine_done(res["machine"])
    H.write_result(a.out, res)


if __name__ == "__main__":
    main()
