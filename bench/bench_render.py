"""Render benchmark of the wgpu tier against the numpy cpu tier and a bare-wgpu floor.

For 10k, 100k, 1M and 4M points at 1280x720 on the adapter found, the median frame time
(upload of the ticks's dirty 1% + cull + raster + output = read_image), interleaved frame by
frame in one process, of:

* ``compute`` — the tier with ``render.raster: compute`` (fused tests + atomic depth keys +
  per-pixel resolve; frustum culling and turbo colour by intensity on, 2 px squares);
* ``quads`` — the tier with ``render.raster: quads`` (cull + compaction + indirect draw);
* ``floor`` — a bare wgpu program measured in the same run: the same points uploaded once,
  drawn as 2 px instanced quads pulled from a storage buffer (depth test, one colour, no
  culling/sampling/colour), same output readback;
* ``cpu``   — :class:`pointflow.render.cpu.CpuRenderer` (skipped above ``--cpu-max``).

Also: each method's ``streamed`` wall time per frame (frames back to back, 1% rewritten each,
no readback: what a live window costs; ``*_streamed_gpoints_per_s``), each method's image
error against the cpu tier (fraction of pixels that differ), bytes
and time of incremental vs full upload when 1% of the ring changes per tick, and the cost of
a pick with each method. ``--cpu-raster`` measures the cpu tier's compiled raster method (numba) against the wgpu
compute method on this adapter and a compiled bare floor, interleaved (with ``--install``:
the ``cpu_raster.json`` that ``backend: auto`` reads). ``--raster-crossover`` measures compute vs quads over point sizes
(with ``--install`` written to the user cache that ``render.raster: auto`` reads; see
:mod:`pointflow.render.calibration`); ``--edl`` measures eye-dome lighting on vs off.
Scene: ``../shared/data/autzen_trim.laz`` tiled to N points when present (georeferenced: x ~ 6.4e5 ft), else a synthetic terrain.

    .venv/bin/python bench/bench_render.py            # ~3-4 min on 2 cores (lavapipe)
    .venv/bin/python bench/bench_render.py --quick    # 10k/100k/1M, fewer repeats

Writes ``bench/results/render.json`` and ``bench/results/render.png``.
"""
from __future__ import annotations

import argparse
import os
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

import _harness
from _harness import median_ms
from _harness.scenes import H, W, base_cloud, camera_for, make_frame, streamed_frames, tiled
from pointflow.config import RenderConfig
from pointflow.render.base import FrameInput
from pointflow.render.camera import Camera
from pointflow.render.wgpu_tier import WgpuRenderer, select_adapter

RESULTS = _harness.RESULTS


# ----------------------------------------------------------------------------- floor
FLOOR_WGSL = r"""
@group(0) @binding(0) var<uniform> vp: mat4x4<f32>;
@group(0) @binding(1) var<storage, read> pos: array<f32>;
@vertex fn vs(@builtin(vertex_index) vi: u32, @builtin(instance_index) ii: u32) -> @builtin(position) vec4<f32> {
  let p = vec3<f32>(pos[3u * ii], pos[3u * ii + 1u], pos[3u * ii + 2u]);
  let c = vp * vec4<f32>(p, 1.0);
  var q = array<vec2<f32>, 6>(vec2<f32>(-1.0, -1.0), vec2<f32>(1.0, -1.0), vec2<f32>(-1.0, 1.0),
                              vec2<f32>(-1.0, 1.0), vec2<f32>(1.0, -1.0), vec2<f32>(1.0, 1.0));
  return vec4<f32>(c.xy + q[vi] * vec2<f32>(2.0 / 1280.0, 2.0 / 720.0) * c.w, c.z, c.w);
}
@fragment fn fs() -> @location(0) vec4<f32> { return vec4<f32>(1.0, 1.0, 1.0, 1.0); }
"""


class Floor:
    """The bare wgpu program: upload once, draw n 2 px instanced quads, read the image back."""

    def __init__(self, adapter, frame: FrameInput, cam: Camera):
        import wgpu
        self.wgpu = wgpu
        self.dev = adapter.request_device_sync(required_limits={
            "max-storage-buffer-binding-size": adapter.limits["max-storage-buffer-binding-size"],
            "max-buffer-size": adapter.limits["max-buffer-size"]})
        d, BU, TU = self.dev, wgpu.BufferUsage, wgpu.TextureUsage
        self.n = frame.size
        pos = np.ascontiguousarray(frame.positions, np.float32)
        self.pos = d.create_buffer_with_data(data=pos, usage=BU.STORAGE)
        vp = np.ascontiguousarray(cam.view_proj(W, H, frame.origin).T, np.float32)
        self.ubo = d.create_buffer_with_data(data=vp, usage=BU.UNIFORM)
        mod = d.create_shader_module(code=FLOOR_WGSL)
        self.pipe = d.create_render_pipeline(
            layout="auto", vertex={"module": mod, "entry_point": "vs", "buffers": []},
            primitive={"topology": "triangle-list"},
            depth_stencil={"format": "depth32float", "depth_write_enabled": True, "depth_compare": "less"},
            multisample={"count": 1},
            fragment={"module": mod, "entry_point": "fs", "targets": [{"format": "rgba8unorm"}]})
        self.bg = d.create_bind_group(layout=self.pipe.get_bind_group_layout(0), entries=[
            {"binding": 0, "resource": {"buffer": self.ubo}}, {"binding": 1, "resource": {"buffer": self.pos}}])
        self.tex = d.create_texture(size=(W, H, 1), format="rgba8unorm", usage=TU.RENDER_ATTACHMENT | TU.COPY_SRC)
        self.depth = d.create_texture(size=(W, H, 1), format="depth32float", usage=TU.RENDER_ATTACHMENT)
        self.rb = d.create_buffer(size=W * 4 * H, usage=BU.MAP_READ | BU.COPY_DST)

    def frame(self) -> None:
        wgpu = self.wgpu
        enc = self.dev.create_command_encoder()
        rp = enc.begin_render_pass(
            color_attachments=[{"view": self.tex.create_view(), "load_op": "clear", "store_op": "store",
                                "clear_value": (0, 0, 0, 1)}],
            depth_stencil_attachment={"view": self.depth.create_view(), "depth_clear_value": 1.0,
                                      "depth_load_op": "clear", "depth_store_op": "store"})
        rp.set_pipeline(self.pipe)
        rp.set_bind_group(0, self.bg)
        rp.draw(6, self.n)
        rp.end()
        enc.copy_texture_to_buffer({"texture": self.tex}, {"buffer": self.rb, "bytes_per_row": W * 4,
                                                           "rows_per_image": H}, (W, H, 1))
        self.dev.queue.submit([enc.finish()])
        self.rb.map_sync(wgpu.MapMode.READ)
        np.frombuffer(self.rb.read_mapped(), np.uint8).copy()
        self.rb.unmap()

    def close(self) -> None:
        for b in (self.pos, self.ubo, self.rb):
            b.destroy()
        self.dev.destroy()


# ----------------------------------------------------------------------------- main
METHODS = ("quads", "compute")


def image_error(img: np.ndarray, ref: np.ndarray) -> float:
    """Fraction of pixels whose RGB differs from the reference."""
    return float((img[..., :3] != ref[..., :3]).any(axis=-1).mean())


def run(sizes: list[int], reps: dict[int, int], cpu_max: int, cpu_compute: bool = False) -> dict[str, Any]:
    adapter, why = select_adapter()
    if adapter is None:
        raise SystemExit(f"no wgpu adapter: {why}")
    machine = _harness.machine(adapter.summary)
    base, inten0, scene = base_cloud()
    cfg = RenderConfig(size=[W, H], color_by="intensity", colormap="turbo", point_size=2.0, gpu_timestamps=True)
    rows = []
    extra: dict[str, Any] = {}
    for n in sizes:
        world, inten = tiled(base, inten0, n)
        f = make_frame(world, inten)
        del world
        cam = camera_for(f.positions.astype(np.float64) + f.origin)
        k = reps.get(n, 3)
        row: dict[str, Any] = {"points": n, "repeats": k}
        # both raster methods of the tier: steady state, 1% of the ring rewritten per tick
        # (dirty range), output = read_image; interleaved frame by frame with the floor so all
        # three see the same load on this shared machine (lavapipe runs on the CPU cores)
        rs = {m: WgpuRenderer(replace(cfg, raster=m), n, ["intensity"], adapter=adapter) for m in METHODS}
        imgs = {}
        for m, r in rs.items():
            r.render(f, cam)
            imgs[m] = r.read_image()
        step = max(n // 100, 1)
        state = {"head": 0}
        last: dict[str, dict[str, Any]] = {m: {} for m in METHODS}

        def tick(m: str, a: int, b: int) -> None:
            f.dirty = [(a, b)]
            st = rs[m].render(f, cam)
            rs[m].read_image()
            last[m]["st"] = st
            last[m].setdefault("upload_ms", []).append(st.timings_ms["upload"])

        fl = Floor(adapter, f, cam)
        fl.frame()
        times: dict[str, list[float]] = {m: [] for m in (*METHODS, "floor")}
        cc = None
        if cpu_compute:  # the cpu tier's compiled raster, in the same interleaving
            from pointflow.render.cpu_compute import CpuComputeRenderer
            cc = CpuComputeRenderer(replace(cfg, backend="cpu", raster="compute"), n, ["intensity"])
            f.dirty = None
            cc.render(f, cam)
            times["cpu_compute"] = []
        for i in range(k):
            a = state["head"]
            b = min(a + step, n)
            state["head"] = b % n
            order = _harness.order(METHODS, i)
            for m in order:
                t0 = time.perf_counter()
                tick(m, a, b)
                times[m].append((time.perf_counter() - t0) * 1e3)
            t0 = time.perf_counter()
            fl.frame()
            times["floor"].append((time.perf_counter() - t0) * 1e3)
            if cc is not None:
                f.dirty = [(a, b)]
                t0 = time.perf_counter()
                cc.render(f, cam)
                imgs["cpu_compute"] = cc.read_image()
                times["cpu_compute"].append((time.perf_counter() - t0) * 1e3)
        fl.close()
        if cc is not None:
            row["cpu_compute_threads"] = cc.info()["threads"]
            row["cpu_compute_vs_floor"] = float(np.median(times["cpu_compute"])) / float(np.median(times["floor"]))
            row["cpu_compute_image_error_vs_wgpu_compute"] = image_error(imgs["cpu_compute"], imgs["compute"])
            del cc
        for m, ts in times.items():
            row[f"{m}_ms"], row[f"{m}_all_ms"] = float(np.median(ts)), ts
        tf = np.asarray(times["floor"])
        for m in METHODS:
            tm = np.asarray(times[m])
            row[f"{m}_vs_floor"] = row[f"{m}_ms"] / row["floor_ms"]
            row[f"floor_over_{m}_per_frame_median"] = float(np.median(tf / tm))
            st = last[m]["st"]
            row[f"{m}_drawn"] = st.drawn
            row[f"{m}_upload_bytes_1pct"] = st.uploaded_bytes
            row[f"{m}_gpu_ms"] = {kk: v for kk, v in st.timings_ms.items() if kk.startswith("gpu")}
            row[f"{m}_cpu_ms"] = st.timings_ms.get("cpu_total")
        # a live view's frames: back to back without readback (what a window presents), each
        # method's wall time per frame; the tier's wait keeps at most two frames in flight
        for m in METHODS:
            per: list[float] = []
            for _ in range(3):
                ms, state["head"] = streamed_frames(rs[m], f, cam, max(k, 10), state["head"])
                per.append(ms)
            row[f"{m}_streamed_ms"] = float(np.median(per))
            row[f"{m}_streamed_gpoints_per_s"] = n / (row[f"{m}_streamed_ms"] * 1e-3) / 1e9
        row["quads_over_compute_per_frame_median"] = float(np.median(np.asarray(times["quads"]) /
                                                                     np.asarray(times["compute"])))
        row["compute_keys"] = rs["compute"].info()["compute_keys"]
        r = rs["compute"]
        if n == 1_000_000 or n == max(sizes):
            # incremental vs full upload (render only, GPU waited on by read_image in both)
            full_up: list[float] = []

            def full():
                f.dirty = None
                full_up.append(r.render(f, cam).timings_ms["upload"])
                r.read_image()
            full_ms, _ = median_ms(full, max(2, k // 2))
            f.dirty = None
            full_bytes = r.render(f, cam).uploaded_bytes
            r.read_image()
            up = {"points": n, "full_bytes": full_bytes, "incremental_bytes": row["compute_upload_bytes_1pct"],
                  "full_frame_ms": full_ms, "incremental_frame_ms": row["compute_ms"],
                  "bytes_ratio": row["compute_upload_bytes_1pct"] / full_bytes,
                  "full_upload_ms": float(np.median(full_up)),
                  "incremental_upload_ms": float(np.median(last["compute"]["upload_ms"]))}
            extra.setdefault("upload", []).append(up)
            # pick cost on the last frame, both methods, interleaved
            xs = np.random.default_rng(1).uniform([W * 0.3, H * 0.3], [W * 0.7, H * 0.7], size=(7, 2)).tolist()
            pk: dict[str, list[float]] = {m: [] for m in METHODS}
            for m in METHODS:
                rs[m].render(f, cam)
                rs[m].read_image()
            for x, y in xs * 2:
                for m in METHODS:
                    t0 = time.perf_counter()
                    rs[m].pick(x, y)
                    pk[m].append((time.perf_counter() - t0) * 1e3)
            agree = sum(rs["quads"].pick(x, y) == rs["compute"].pick(x, y) for x, y in xs)
            extra.setdefault("pick", []).append({"points": n, "radius": cfg.pick_radius,
                                                 **{f"{m}_pick_ms": float(np.median(v)) for m, v in pk.items()},
                                                 "same_answer": f"{agree}/{len(xs)}"})
        for rr in rs.values():
            rr.close()

        if n <= cpu_max:
            from pointflow.render.cpu import CpuRenderer
            c = CpuRenderer(cfg, n, ["intensity"])

            def cpu_frame():
                f.dirty = None
                c.render(f, cam)
                imgs["cpu"] = c.read_image()
            row["cpu_ms"], row["cpu_all_ms"] = median_ms(cpu_frame, max(1, min(k, 3)), warm=0)
            row["speedup_vs_cpu"] = row["cpu_ms"] / row["compute_ms"]
            for m in METHODS:
                row[f"{m}_image_error_vs_cpu"] = image_error(imgs[m], imgs["cpu"])
        rows.append(row)
        print(f"  {n:>9,}: quads {row['quads_ms']:8.1f} ms  compute {row['compute_ms']:8.1f} ms  floor "
              f"{row['floor_ms']:8.1f} ms  floor/compute x{row['floor_over_compute_per_frame_median']:.2f}  "
              f"quads/compute x{row['quads_over_compute_per_frame_median']:.2f}  "
              f"err vs cpu {row.get('compute_image_error_vs_cpu', float('nan')):.2e}", flush=True)
        del f
    return {"scene": scene, "size": [W, H], "adapter": adapter.summary, "adapter_choice": why,
            "machine": _harness.machine_done(machine), "rows": rows, **extra}


def _race(adapter, f: FrameInput, cam: Camera, cfg: RenderConfig, n: int, reps: int) -> dict[str, float]:
    """Median frame ms of both methods, interleaved (ABBA), after one warm-up frame each."""
    rs = {m: WgpuRenderer(replace(cfg, raster=m), n, ["intensity"], adapter=adapter) for m in METHODS}
    ts: dict[str, list[float]] = {m: [] for m in METHODS}
    try:
        for i in range(reps + 1):
            for m in _harness.order(METHODS, i):
                t0 = time.perf_counter()
                rs[m].render(f, cam)
                rs[m].read_image()
                if i:
                    ts[m].append((time.perf_counter() - t0) * 1e3)
    finally:
        for r in rs.values():
            r.close()
    return {f"{m}_ms": float(np.median(v)) for m, v in ts.items()}


def _tiled_scene(n: int) -> tuple[Any, str, FrameInput, Camera]:
    """(adapter, scene name, frame, camera) of the main benchmark's scene at n points."""
    adapter, _why = select_adapter()
    base, inten0, scene = base_cloud()
    world, inten = tiled(base, inten0, n)
    return adapter, scene, make_frame(world, inten), camera_for(world)


def raster_crossover(n: int, sizes_px: list[float], counts: list[int], reps: int) -> dict[str, Any]:
    """Compute vs quads frame time (interleaved, medians) over point sizes at n points and over
    point counts at 2 px: ``max_compute_point_px`` = the largest size up to which compute was
    faster at every size; ``min_compute_points_per_pixel`` = the smallest count from which it
    was faster at every larger count, per target pixel (its resolve pass is per pixel)."""
    adapter, scene, f, cam = _tiled_scene(n)
    out, best, ok = [], 0.0, True
    for s in sizes_px:
        cfg = RenderConfig(size=[W, H], color_by="intensity", point_size=float(s), gpu_timestamps=False)
        row = {"point_px": s, **_race(adapter, f, cam, cfg, n, reps)}
        row["quads_over_compute"] = row["quads_ms"] / row["compute_ms"]
        out.append(row)
        print(f"  {n:,} points, {s:5.1f} px: quads {row['quads_ms']:8.1f} ms  compute {row['compute_ms']:8.1f} ms  "
              f"x{row['quads_over_compute']:.2f}", flush=True)
        if ok and row["compute_ms"] < row["quads_ms"]:
            best = float(s)
        else:
            ok = False
    by_count = []
    cfg = RenderConfig(size=[W, H], color_by="intensity", point_size=2.0, gpu_timestamps=False)
    for c in counts:
        w2, i2 = tiled(base, inten0, c)
        fc = make_frame(w2, i2)
        row = {"points": c, **_race(adapter, fc, camera_for(w2), cfg, c, reps)}
        row["quads_over_compute"] = row["quads_ms"] / row["compute_ms"]
        by_count.append(row)
        print(f"  {c:>9,} points, 2 px: quads {row['quads_ms']:8.1f} ms  compute {row['compute_ms']:8.1f} ms  "
              f"x{row['quads_over_compute']:.2f}", flush=True)
    from_n = counts[-1] * 2
    for row in reversed(by_count):
        if row["compute_ms"] < row["quads_ms"]:
            from_n = row["points"]
        else:
            break
    return {"points": n, "adapter": adapter.summary, "scene": scene, "size": [W, H], "by_point_px": out,
            "by_points": by_count, "max_compute_point_px": best, "min_compute_points": from_n,
            "min_compute_points_per_pixel": round(from_n / (W * H), 6),
            "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "machine": _harness.machine_done(_harness.machine(adapter.summary))}


def edl_cost(n: int, reps: int) -> dict[str, Any]:
    """Frame time with eye-dome lighting on vs off for both methods at n points (same scene
    and frame as the main benchmark: 1% of the ring rewritten per frame, output =
    read_image), the four renderers interleaved frame by frame in rotating order."""
    from pointflow.config import EdlConfig
    adapter, scene, f, cam = _tiled_scene(n)
    cfg = RenderConfig(size=[W, H], color_by="intensity", colormap="turbo", point_size=2.0, gpu_timestamps=False)
    keys = [(m, e) for m in METHODS for e in (False, True)]
    rs = {k: WgpuRenderer(replace(cfg, raster=k[0], edl=EdlConfig(enabled=k[1])), n, ["intensity"],
                          adapter=adapter) for k in keys}
    ts: dict[Any, list[float]] = {k: [] for k in keys}
    cpu: dict[Any, list[float]] = {k: [] for k in keys}  # process CPU time: lavapipe's threads are ours
    step, head = max(n // 100, 1), 0
    try:
        for k in keys:  # warm-up (pipelines compiled, buffers uploaded)
            rs[k].render(f, cam)
            rs[k].read_image()
        for i in range(reps):
            a, b = head, min(head + step, n)
            head = b % n
            order = keys[i % len(keys):] + keys[:i % len(keys)]
            if i % 2:
                order = order[::-1]
            for k in order:
                f.dirty = [(a, b)]
                t0, c0 = time.perf_counter(), time.process_time()
                rs[k].render(f, cam)
                rs[k].read_image()
                ts[k].append((time.perf_counter() - t0) * 1e3)
                cpu[k].append((time.process_time() - c0) * 1e3)
    finally:
        for r in rs.values():
            r.close()
    out: dict[str, Any] = {"points": n, "size": [W, H], "repeats": reps, "adapter": adapter.summary, "scene": scene,
                           "edl": {"strength": 1.0, "radius_px": 1.4}, "measured_at": time.strftime(
                               "%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                           "machine": _harness.machine_done(_harness.machine(adapter.summary))}
    for m in METHODS:
        off, on = np.asarray(ts[(m, False)]), np.asarray(ts[(m, True)])
        out[m] = {"off_ms": float(np.median(off)), "on_ms": float(np.median(on)),
                  "on_over_off": float(np.median(on) / np.median(off)),
                  "on_over_off_per_frame_median": float(np.median(on / off)),
                  "off_all_ms": off.tolist(), "on_all_ms": on.tolist()}
        coff, con = np.asarray(cpu[(m, False)]), np.asarray(cpu[(m, True)])
        out[m].update({"off_cpu_ms": float(np.median(coff)), "on_cpu_ms": float(np.median(con)),
                       "cpu_on_over_off": float(np.median(con) / np.median(coff)),
                       "off_all_cpu_ms": coff.tolist(), "on_all_cpu_ms": con.tolist()})
        print(f"  {n:,} points, {m:8s}: EDL off {out[m]['off_ms']:8.1f} ms  on {out[m]['on_ms']:8.1f} ms  "
              f"on/off x{out[m]['on_over_off']:.3f} (per-frame median x{out[m]['on_over_off_per_frame_median']:.3f}); "
              f"CPU time on/off x{out[m]['cpu_on_over_off']:.3f}", flush=True)
    return out


def cpu_raster(sizes: list[int], reps: dict[int, int]) -> dict[str, Any]:
    """The cpu tier's compiled raster (``raster: compute``) against the wgpu compute method on
    this adapter and a compiled bare floor (the same chunking, float64 projection and key
    write, no rules, no resolve), per frame interleaved in rotating order: 1% of the ring
    rewritten per frame (dirty range), output = read_image. 1280x720, 2 px squares, turbo by
    intensity. Also the compiled method at 1 thread and at every thread numba has."""
    import numba

    from _harness.cpu_floor import floor_kernel
    from pointflow.render.cpu_compute import CHUNKS_PER_THREAD, TUNE_FRAMES, CpuComputeRenderer
    machine = _harness.machine()
    adapter, why = select_adapter()
    base, inten0, scene = base_cloud()
    cfg = RenderConfig(size=[W, H], color_by="intensity", colormap="turbo", point_size=2.0, gpu_timestamps=False)
    threads = numba.get_num_threads()
    rows = []
    for n in sizes:
        world, inten = tiled(base, inten0, n)
        f = make_frame(world, inten)
        cam = camera_for(world)
        del world
        k = reps.get(n, 5)
        # cpu_compute: the renderer as shipped (per frame 1 thread or all, whichever drew faster
        # lately); cpu_compute_1thread: numba limited to 1 thread
        cc = CpuComputeRenderer(replace(cfg, backend="cpu", raster="compute"), n, ["intensity"])
        other = "points" if cc.bands else "bands"
        os.environ["POINTFLOW_CPU_RASTER_SPLIT"] = other
        try:  # the other way of sharing the work between the threads
            cc_other = CpuComputeRenderer(replace(cfg, backend="cpu", raster="compute"), n, ["intensity"])
        finally:
            del os.environ["POINTFLOW_CPU_RASTER_SPLIT"]
        wg = WgpuRenderer(replace(cfg, raster="compute"), n, ["intensity"], adapter=adapter) if adapter else None
        floor_loop = floor_kernel()
        vp = np.ascontiguousarray(cam.view_proj(W, H, f.origin), np.float64)
        fpos = np.ascontiguousarray(f.positions, np.float32)

        def floor() -> None:
            T = cc.threads  # the thread count the renderer chose for its last frame
            keys = cc._buffers(T)
            C = T if cc.bands else T * CHUNKS_PER_THREAD
            prev = numba.set_parallel_chunksize(1)  # as the renderer runs its raster pass
            numba.set_num_threads(T)
            try:
                floor_loop(keys, T, C, cc.bands, fpos, n, 0, n, W, H, vp, 1.0)
            finally:
                numba.set_parallel_chunksize(prev)
                numba.set_num_threads(threads)

        def one(r) -> Callable[[], None]:
            def go() -> None:
                r.render(f, cam)
                r.read_image()
            return go

        def single() -> None:
            numba.set_num_threads(1)
            try:
                one(cc)()
            finally:
                numba.set_num_threads(threads)

        fns = {"cpu_compute": one(cc), f"cpu_compute_{other}": one(cc_other), "cpu_compute_1thread": single,
               "floor": floor}
        if wg is not None:
            fns["wgpu_compute"] = one(wg)
        names = list(fns)
        ts: dict[str, list[float]] = {m: [] for m in names}
        step, head = max(n // 100, 1), 0
        for m in names:  # warm-up; the renderers also settle their thread count (2 x TUNE_FRAMES frames)
            f.dirty = None
            for _ in range(1 + (2 * TUNE_FRAMES if m.startswith("cpu_compute") else 0)):
                fns[m]()
        for i in range(k):
            a, b = head, min(head + step, n)
            head = b % n
            order = names[i % len(names):] + names[:i % len(names)]
            for m in order:
                f.dirty = [(a, b)]
                t0 = time.perf_counter()
                fns[m]()
                ts[m].append((time.perf_counter() - t0) * 1e3)
        img_cc = cc.read_image()
        row: dict[str, Any] = {"points": n, "repeats": k, "threads": threads,
                               "frames_per_thread_count": {str(t): c for t, c in sorted(cc.frames_at.items())},
                               "tune_ms": {"/".join(map(str, t)) if isinstance(t, tuple) else str(t): v for t, v in cc._tune.items()},
                               "split": cc.split_mode, "other_split": other}
        for m, v in ts.items():
            row[f"{m}_ms"], row[f"{m}_all_ms"] = float(np.median(v)), v
        c = np.asarray(ts["cpu_compute"])
        row["floor_over_cpu_compute_per_frame_median"] = float(np.median(np.asarray(ts["floor"]) / c))
        row["one_thread_over_all_per_frame_median"] = float(np.median(np.asarray(ts["cpu_compute_1thread"]) / c))
        row["other_split_over_default_per_frame_median"] = float(np.median(np.asarray(ts[f"cpu_compute_{other}"]) / c))
        if wg is not None:
            row["wgpu_over_cpu_compute_per_frame_median"] = float(np.median(np.asarray(ts["wgpu_compute"]) / c))
            row["image_error_cpu_compute_vs_wgpu_compute"] = image_error(img_cc, wg.read_image())
            wg.close()
        if n <= 1_000_000:
            from pointflow.render.cpu import CpuRenderer
            ref = CpuRenderer(cfg, n, ["intensity"])
            f.dirty = None
            ref.render(f, cam)
            row["image_error_vs_reference"] = image_error(img_cc, ref.read_image())
        rows.append(row)
        print(f"  {n:>9,}: cpu compute {row['cpu_compute_ms']:7.1f} ms ({threads} threads; 1 thread "
              f"{row['cpu_compute_1thread_ms']:7.1f})  wgpu compute {row.get('wgpu_compute_ms', float('nan')):7.1f} ms  "
              f"floor {row['floor_ms']:7.1f} ms  wgpu/cpu x{row.get('wgpu_over_cpu_compute_per_frame_median', float('nan')):.2f}  "
              f"floor/cpu x{row['floor_over_cpu_compute_per_frame_median']:.2f}  {other}/{row['split']} "
              f"x{row['other_split_over_default_per_frame_median']:.2f}", flush=True)
        del f, cc, cc_other
    sp = {str(r["points"]): round(r["wgpu_over_cpu_compute_per_frame_median"], 2) for r in rows
          if "wgpu_over_cpu_compute_per_frame_median" in r}
    faster = [int(p) for p, v in sp.items() if v > 1.0]
    lim = None if faster and len(faster) == len(sp) else (max(faster) if faster else 0)
    return {"scene": scene, "size": [W, H], "adapter": adapter.summary if adapter else None,
            "adapter_type": adapter.info.get("adapter_type", "") if adapter else None, "adapter_choice": why,
            "numba": numba.__version__, "threads": threads, "rows": rows,
            "faster_up_to_points": lim, "speedup": sp,
            "machine": _harness.machine_done({**machine, "adapter": adapter.summary if adapter else None}),
            "measured_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "command": _harness.command()}


def _frame_time_axes(res: dict[str, Any], figsize: tuple[float, float]):
    """(figure, axes, rows, point counts) of a frame time vs points chart; None without matplotlib."""
    if (plt := _harness.pyplot()) is None:
        return None
    fig, ax = plt.subplots(figsize=figsize)
    return fig, ax, res["rows"], [r["points"] for r in res["rows"]]


def _save_frame_time_chart(fig, ax, path: Path, **legend: Any) -> None:
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(**legend)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    import matplotlib.pyplot as plt

    plt.close(fig)


def cpu_raster_chart(res: dict[str, Any], path: Path) -> None:
    """Frame time per method against points (log-log), ratios to wgpu compute and the floor noted."""
    if (got := _frame_time_axes(res, (7.2, 4.6))) is None:
        return
    fig, ax, rows, n = got
    series = [("wgpu_compute_ms", "o-", "wgpu compute method on " + str(res.get("adapter") or "?").split(" (")[0]),
              ("cpu_compute_ms", "*-", f"cpu compiled raster, {res['threads']} threads (split {rows[0].get('split', 'points')})"),
              ("cpu_compute_1thread_ms", "v:", "cpu compiled raster, 1 thread"),
              (f"cpu_compute_{rows[0].get('other_split', 'bands')}_ms", "x:",
               f"cpu compiled raster, split by {rows[0].get('other_split', 'bands')}"),
              ("floor_ms", "s--", "compiled bare floor (projection + key write)")]
    for key, style, label in series:
        if all(key in r for r in rows):
            ax.loglog(n, [r[key] for r in rows], style, label=label)
    for r in rows:
        if "wgpu_over_cpu_compute_per_frame_median" in r:
            ax.annotate(f"x{r['wgpu_over_cpu_compute_per_frame_median']:.2f} vs wgpu\n"
                        f"floor/cpu {r['floor_over_cpu_compute_per_frame_median']:.2f}",
                        (r["points"], r["cpu_compute_ms"]), xytext=(6, -26), textcoords="offset points", fontsize=7.5)
    ax.set_xlabel("points")
    ax.set_ylabel("median frame time, ms (interleaved)")
    ax.set_title(f"{res['size'][0]}x{res['size'][1]}, 2 px, turbo by intensity, 1% dirty per frame; "
                 f"{res.get('machine', {}).get('cores', res.get('cpu_count'))} cores", fontsize=9)
    _save_frame_time_chart(fig, ax, path, fontsize=7.5, loc="upper left")


def table(res: dict[str, Any]) -> str:
    out = [f"render benchmark — {res['adapter']} — {res['scene']} — {W}x{H}, 2 px squares, turbo by intensity",
           f"{'points':>10} {'floor ms':>9} {'quads ms':>9} {'compute ms':>10} {'floor/comp':>10} "
           f"{'quads/comp':>10} {'cpu ms':>8} {'err quads':>9} {'err comp':>9} {'gpu raster':>10} {'resolve':>8}"]
    for r in res["rows"]:
        g = r.get("compute_gpu_ms", {})
        out.append(f"{r['points']:>10,} {r['floor_ms']:>9.1f} {r['quads_ms']:>9.1f} {r['compute_ms']:>10.1f} "
                   f"{r['floor_over_compute_per_frame_median']:>10.2f} {r['quads_over_compute_per_frame_median']:>10.2f} "
                   f"{r.get('cpu_ms', float('nan')):>8.1f} {r.get('quads_image_error_vs_cpu', float('nan')):>9.1e} "
                   f"{r.get('compute_image_error_vs_cpu', float('nan')):>9.1e} "
                   f"{g.get('gpu_compute', float('nan')):>10.1f} {g.get('gpu_draw', float('nan')):>8.1f}")
    for u in res.get("upload", []):
        out.append(f"upload at {u['points']:,} points, 1% changed per tick: incremental {u['incremental_bytes']:,} B "
                   f"in {u['incremental_upload_ms']:.2f} ms ({u['incremental_frame_ms']:.1f} ms/frame) vs full "
                   f"{u['full_bytes']:,} B in {u['full_upload_ms']:.2f} ms ({u['full_frame_ms']:.1f} ms/frame); "
                   f"bytes ratio {u['bytes_ratio']:.4f}")
    for p in res.get("pick", []):
        out.append(f"pick at {p['points']:,} points (radius {p['radius']} px): compute {p['compute_pick_ms']:.1f} ms, "
                   f"quads {p['quads_pick_ms']:.1f} ms (same answer {p['same_answer']})")
    return "\n".join(out)


def chart(res: dict[str, Any], path: Path) -> None:
    if (got := _frame_time_axes(res, (7, 4.5))) is None:
        return
    fig, ax, rows, n = got
    ax.loglog(n, [r["compute_ms"] for r in rows], "o-", label="wgpu tier, compute method (fused tests + atomics)")
    ax.loglog(n, [r["quads_ms"] for r in rows], "d-", label="wgpu tier, quads method (cull + compaction + draw)")
    ax.loglog(n, [r["floor_ms"] for r in rows], "s--", label="bare-wgpu floor (2 px instanced quads)")
    cpu = [(r["points"], r["cpu_ms"]) for r in rows if "cpu_ms" in r]
    if cpu:
        ax.loglog(*zip(*cpu), "^-", label="cpu tier (numpy)")
    ax.set_xlabel("points")
    ax.set_ylabel("median frame time, ms")
    ax.set_title(f"frame = upload 1% + cull + raster + readback, {W}x{H}\n{res['adapter']}", fontsize=9)
    _save_frame_time_chart(fig, ax, path, fontsize=8)


def main(argv: Optional[list[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10k/100k/1M with fewer repeats")
    ap.add_argument("--sizes", type=int, nargs="*", default=None)
    ap.add_argument("--cpu-max", type=int, default=1_000_000, help="largest size timed on the cpu tier")
    ap.add_argument("--out", default=str(RESULTS / "render.json"))
    ap.add_argument("--raster-crossover", action="store_true",
                    help="only measure compute vs quads over point sizes at 1M points and write "
                         "bench/results/raster_crossover.json (--install: also the user cache that "
                         "render.raster: auto reads)")
    ap.add_argument("--edl", action="store_true",
                    help="only measure eye-dome lighting on vs off for both methods at 1M points "
                         "(writes bench/results/edl.json)")
    ap.add_argument("--install", action="store_true",
                    help="with --raster-crossover: also write the result to the user cache that "
                         "render.raster: auto reads (pointflow.render.calibration)")
    ap.add_argument("--with-cpu-compute", action="store_true",
                    help="also time the cpu tier's compiled raster in the main run's interleaving")
    ap.add_argument("--cpu-raster", action="store_true",
                    help="only measure the cpu tier's compiled raster vs wgpu compute and a compiled floor "
                         "at 100k/1M/4M (bench/results/cpu_raster.json; --install: the user cache that "
                         "backend: auto reads)")
    a = ap.parse_args(argv)
    if a.cpu_raster:
        sizes = a.sizes or [100_000, 1_000_000, 4_000_000]
        res = cpu_raster(sizes, {100_000: 15, 1_000_000: 15, 4_000_000: 5} if not a.quick else {})
        path = Path(a.out) if a.out != str(RESULTS / "render.json") else RESULTS / "cpu_raster.json"
        _harness.write_result(path, res)
        cpu_raster_chart(res, path.with_suffix(".png"))
        if a.install:
            from pointflow.render import calibration
            keep = {k: res[k] for k in ("faster_up_to_points", "speedup", "adapter", "adapter_type", "scene",
                                        "size", "threads", "measured_at", "machine", "command")}
            print(f"installed {calibration.install('cpu_raster.json', keep)}")
        print(f"faster_up_to_points = {res['faster_up_to_points']}, wgpu/cpu speedup {res['speedup']}; wrote {path}")
        return 0
    if a.edl:
        res = edl_cost(1_000_000, 15 if not a.quick else 6)
        path = RESULTS / "edl.json"
        _harness.write_result(path, res)
        print(f"wrote {path}")
        return 0
    if a.raster_crossover:
        res = raster_crossover(1_000_000, [1, 2, 3, 4, 6, 8, 12, 16, 24, 32],
                               [1_000, 3_000, 10_000, 30_000, 100_000, 300_000], 5)
        path = RESULTS / "raster_crossover.json"
        _harness.write_result(path, res)
        if a.install:
            from pointflow.render import calibration
            print(f"installed {calibration.install('raster_crossover.json', res)}")
        print(f"max_compute_point_px = {res['max_compute_point_px']:g}, min_compute_points = "
              f"{res['min_compute_points']:,} ({res['min_compute_points_per_pixel']:g} per pixel); wrote {path}")
        return 0
    sizes = a.sizes or ([10_000, 100_000, 1_000_000] if a.quick else [10_000, 100_000, 1_000_000, 4_000_000])
    reps = {10_000: 15, 100_000: 9, 1_000_000: 5, 4_000_000: 3}
    if a.quick:
        reps = {k: max(2, v // 2) for k, v in reps.items()}
    t0 = time.perf_counter()
    res = run(sizes, reps, a.cpu_max, a.with_cpu_compute)
    res["bench_seconds"] = time.perf_counter() - t0
    out = _harness.write_result(a.out, res)
    chart(res, out.with_suffix(".png"))
    print(table(res))
    print(f"wrote {out} and {out.with_suffix('.png')} in {res['bench_seconds']:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
