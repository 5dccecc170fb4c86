"""docs/map.md's first example in real processes (issue 37): a georeferenced map (UTM-sized
coordinates, written by laspy) and a live sensor.

- Not placed (``source: synthetic`` at the origin, no ``frames:`` block): the auto view frames
  the map and the render stage says once how far apart the two are; the auto view and a camera
  600 m above the map each light the pixels laspy's own points light (within 1 % of them).
- Placed by ``frames.fixed`` and a static transform: both are drawn in one frame, and a pick
  returns a map point and a live point with their true (float64 world) coordinates."""
from __future__ import annotations

import os

import numpy as np
from PIL import Image

from pointflow import Pipeline
from pointflow.render.camera import Camera

from .mapfiles import laspy_points, terrain, write_las
from .test_geo_view import BOUND, UTM, occupancy

N_MAP = 20_000
W, H = 240, 160


def _utm_las(tmp_path) -> tuple[str, np.ndarray]:
    path = write_las(str(tmp_path / "utm.las"), N_MAP, seed=7,
                     pos=terrain(N_MAP, 7) - [700000.0, 5700000.0, 100.0] + UTM)
    return path, laspy_points(path)["positions"]


def _render(**kw) -> dict:
    return {"backend": "cpu", "size": [W, H], "point_size": 2, "output": {"every_n_frames": 100000}, **kw}


def _lit(png: str) -> np.ndarray:
    img = np.asarray(Image.open(png))[..., :3]
    return (img != img[0, 0]).any(axis=-1)


def _drawn_camera(pipe) -> Camera:
    d = pipe.view_state()["camera_drawn"]
    return Camera(eye=d["eye"], target=d["target"], up=d["up"], fov_deg=d["fov_deg"], near=d["near"], far=d["far"])


def test_a_map_far_from_an_unplaced_sensor_is_framed_and_drawn(tmp_path):
    las, world = _utm_las(tmp_path)
    cfg = {"source": {"transport": "synthetic", "options": {"scan_hz": 10, "points_per_scan": 2000}},
           "ring": {"max_points": 20_000}, "render": _render(),
           "map": {"path": las, "point_budget": 50_000, "cache_dir": str(tmp_path / "cache")}}
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path / "out")) as pipe:
        render = lambda: pipe.stats()["stages"]["render"]  # noqa: E731
        pipe.wait(180, until=lambda: render().get("map_points", 0) >= N_MAP and render().get("map_apart_m"))
        assert abs(render()["map_apart_m"] - np.linalg.norm(UTM[:2] + 200)) < 2000, "the warning says how far"
        for name in ("auto", "top"):
            if name == "top":
                pipe.camera(eye=list(UTM + [200, 200, 600]), target=list(UTM + [200, 200, 0]), up=[0, 1, 0])
            cam = _drawn_camera(pipe)
            got = _lit(pipe.save_frame(str(tmp_path / f"{name}.png")))
            want = occupancy(world, cam, 2.0, W, H)
            assert want.mean() > 0.05, f"{name}: laspy's picture is a real one"
            diff = (got != want).mean()
            assert diff <= BOUND * want.mean(), f"{name}: {got.mean():.2%} lit, laspy's {want.mean():.2%}, {diff:.3%} differ"
        assert cam.near > 100 and cam.far < 2000, "near and far from the map in front, not from 6,600 km of scene"


def test_a_sensor_placed_in_the_map_draws_both_with_true_coordinates(tmp_path):
    las, world = _utm_las(tmp_path)
    g = np.stack(np.meshgrid(np.arange(0, 40, 1.0), np.arange(0, 40, 1.0)), -1).reshape(-1, 2) - 20
    local = np.column_stack([g, np.full(len(g), 60.0)])  # a plane 60 m above the sensor, in its own frame
    live = str(tmp_path / "live.npz")
    np.savez(live, x=local[:, 0], y=local[:, 1], z=local[:, 2])
    at = UTM + [200.0, 200.0, 0.0]  # where the sensor stands in the map's coordinates
    cfg = {"source": {"transport": "file", "name": "lidar", "frame_id": "lidar",
                      "options": {"path": live, "realtime": False}},
           "frames": {"fixed": "map", "static": [{"parent": "map", "child": "lidar", "translation": at.tolist()}]},
           "ring": {"max_points": 4000}, "render": _render(color_by="z"),
           "map": {"path": las, "point_budget": 50_000, "cache_dir": str(tmp_path / "cache")}}
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path / "out")) as pipe:
        render = lambda: pipe.stats()["stages"]["render"]  # noqa: E731
        pipe.wait(180, until=lambda: render().get("map_points", 0) >= N_MAP and render()["points_in"] > 0
                  and pipe.stats()["accounting"]["ingest_written"] == len(local))
        assert not render().get("map_apart_m"), "placed: not apart"
        eye, target = at + [0, 0, 500], at.copy()
        pipe.camera(eye=list(eye), target=list(target), up=[0, 1, 0], fov_deg=60.0)
        cam = _drawn_camera(pipe)
        lit = _lit(pipe.save_frame(str(tmp_path / "both.png")))
        truth = local + at

        def px(p):
            from pointflow.render.camera import project_to_pixels

            x, y, _, _ = project_to_pixels(np.asarray([p]) - target, cam.view_proj(W, H, target), W, H)
            return int(x[0]), int(y[0])

        cx, cy = px(truth.mean(axis=0))
        assert lit[cy, cx], "the live plane is drawn over the map's middle"
        p = pipe.pick(cx, cy)
        assert p is not None and p["source"] == "lidar"
        assert np.min(np.linalg.norm(truth - p["position"], axis=1)) < 2e-3, "a live point's true coordinates"
        corner = UTM + [40.0, 40.0, 0.0]
        mx, my = px(corner)
        assert lit[my - 3:my + 4, mx - 3:mx + 4].any(), "the map is drawn around it"
        p = pipe.pick(mx, my)
        assert p is not None and p["source"] == f"map: {las}"
        assert np.min(np.linalg.norm(world - p["position"], axis=1)) < 1e-9, "a map point, exactly the file's"
        assert os.path.exists(las)
