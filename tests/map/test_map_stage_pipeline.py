"""A live source and a map in one pipeline (real processes, files written by laspy, cpu tier):
both drawn in one frame, picking finds each and names its source, the map's points are
exactly the file's, the accounting is exact for both; a broken map file is a one-line error
and the live part goes on."""
from __future__ import annotations

import os

import numpy as np
import pytest
from PIL import Image

from pointflow import Pipeline
from pointflow.render.camera import Camera, project_to_pixels

from .mapfiles import ORIGIN, laspy_points, write_las

W, H = 200, 150
N_MAP = 20_000
#: straight down over the middle of the 400 x 400 m tile
EYE = ORIGIN + [200.0, 200.0, 600.0]
TARGET = ORIGIN + [200.0, 200.0, 0.0]
UP = [0.0, 1.0, 0.0]
BG = np.round(np.array([0.02, 0.02, 0.05]) * 255).astype(np.uint8)


def _live(path: str) -> tuple[str, np.ndarray]:
    """A 40 x 40 m plane of live points floating 60 m above the tile's middle."""
    g = np.stack(np.meshgrid(np.arange(0, 40, 1.0), np.arange(0, 40, 1.0)), -1).reshape(-1, 2)
    pts = np.column_stack([g + ORIGIN[:2] + 180, np.full(len(g), ORIGIN[2] + 60)])
    f = os.path.join(path, "live.npz")
    np.savez(f, x=pts[:, 0], y=pts[:, 1], z=pts[:, 2])
    return f, pts


def _config(live: str, map_path: str, **map_opts) -> dict:
    return {"source": {"transport": "file", "name": "scanner", "options": {"path": live, "realtime": False}},
            "ring": {"max_points": 4000},
            "render": {"backend": "cpu", "size": [W, H], "point_size": 2, "color_by": "z",
                       "output": {"every_n_frames": 100000}},
            "map": {"path": map_path, "point_budget": 50_000, **map_opts}}


def _px(p) -> tuple[int, int]:
    cam = Camera(eye=EYE, target=TARGET, up=UP, fov_deg=60.0)
    px, py, _, _ = project_to_pixels(np.asarray([p], np.float64) - TARGET, cam.view_proj(W, H, TARGET), W, H)
    return int(px[0]), int(py[0])


def test_live_and_map_in_one_pipeline(tmp_path):
    las = write_las(str(tmp_path / "tile.las"), N_MAP, seed=1)
    live, live_pts = _live(str(tmp_path))
    truth = laspy_points(las)
    with Pipeline.from_dict(_config(live, las), out_dir=str(tmp_path)) as pipe:
        render = lambda: pipe.stats()["stages"]["render"]  # noqa: E731
        pipe.wait(120, until=lambda: render().get("map_points", 0) >= N_MAP and render()["points_in"] > 0
                  and pipe.stats()["accounting"]["ingest_written"] == len(live_pts)
                  and pipe.stats()["accounting"].get("map_agrees") is True)  # both stages reported
        assert render()["map_points"] == N_MAP, "the whole map (budget above its points) reached the renderer"
        pipe.camera(eye=list(EYE), target=list(TARGET), up=UP, fov_deg=60.0)
        img = np.asarray(Image.open(pipe.save_frame(str(tmp_path / "both.png"))))[..., :3]

        # both kinds drawn: the live plane in the middle, the map around it
        cx, cy = _px(live_pts.mean(axis=0))
        assert not (img[cy, cx] == BG).all()
        corner = ORIGIN + [60.0, 60.0, 0.0]
        mx, my = _px(corner)
        assert not (img[my - 3:my + 4, mx - 3:mx + 4] == BG).all(axis=-1).all()

        # picking: a live point named by its source, a map point by its file, exact world position
        p = pipe.pick(cx, cy)
        assert p is not None and p["source"] == "scanner"
        assert np.min(np.linalg.norm(live_pts - p["position"], axis=1)) < 1e-3
        p = pipe.pick(mx, my)
        assert p is not None and p["source"] == f"map: {las}"
        d = np.linalg.norm(truth["positions"] - p["position"], axis=1)
        i = int(np.argmin(d))
        assert d[i] < 1e-9, "a picked map point is one of the file's points, in float64"
        assert np.linalg.norm(np.asarray(p["position"])[:2] - corner[:2]) < 10

        # accounting: the live points exactly, the map's points exactly (once both stages
        # reported the same map version: the camera above may have made a new one)
        pipe.wait(60, until=lambda: pipe.stats()["accounting"].get("map_agrees") is True)
        st = pipe.stats()
        acc = st["accounting"]
        assert acc["ingest_received"] == acc["ingest_written"] == len(live_pts)
        assert acc["ring_agrees"] and acc["sources_balanced"]
        assert acc["map_file_points"] == acc["map_points_held"] == acc["map_points_drawn"] == N_MAP
        assert acc["map_agrees"] is True and acc["map_error"] is None
        m = st["stages"]["map"]
        assert m["map_points"] == st["stages"]["render"]["map_points"] == N_MAP
        assert m["map_point_count"] == N_MAP and m["map_error"] is None
        assert m["points_in"] >= N_MAP  # read from the file (each node once while cached)
        assert m["map_nodes"] >= 1 and m["map_cache_bytes"] > 0 and m["map_load_ms_p50"] is not None

        # the profile shows the map: nodes, points drawn, cache use, load latency (its own spans)
        from pointflow.profiling.report import build_profile, format_table

        pipe.wait(60, until=lambda: "map_load" in build_profile(pipe.collector, st)["stages"])  # spans in batches
        prof = build_profile(pipe.collector, st)
        assert prof["map"]["points_drawn"] == N_MAP and prof["map"]["map_nodes"] == m["map_nodes"]
        assert prof["stages"]["map_load"]["count"] >= 1
        assert f"{N_MAP:,} points drawn" in format_table(prof)


def test_a_broken_map_file_is_named_and_the_live_part_goes_on(tmp_path):
    # noise inside a LAZ's compressed points: its header and chunk table pass the load checks
    # (a file cut short is refused at load: tests/map/test_map_path_errors.py)
    las = write_las(str(tmp_path / "tile.laz"), N_MAP, seed=2)
    raw = bytearray(open(las, "rb").read())
    mid = len(raw) // 3
    raw[mid:mid + 4000] = bytes(range(256)) * 15 + bytes(160)
    open(las, "wb").write(bytes(raw))
    live, live_pts = _live(str(tmp_path))
    with Pipeline.from_dict(_config(live, las), out_dir=str(tmp_path)) as pipe:
        pipe.wait(120, until=lambda: pipe.stats()["stages"]["map"].get("map_error") is not None
                  and pipe.stats()["accounting"]["ingest_written"] == len(live_pts)
                  and pipe.stats()["stages"]["render"].get("drawn_count", 0) >= len(live_pts))
        st = pipe.stats()
        m = st["stages"]["map"]
        assert m["map_error"] and las in m["map_error"], m["map_error"]
        assert "\n" not in m["map_error"]
        # one error a map stage incarnation (a loaded machine may have a stage restarted)
        assert m["drops"].get("map_error") == 1 + m["restarts"]
        assert st["stages"]["render"].get("map_points", 0) == 0
        assert st["accounting"]["ingest_written"] == len(live_pts)
        pipe.camera(eye=list(EYE), target=list(TARGET), up=UP, fov_deg=60.0)
        cx, cy = _px(live_pts.mean(axis=0))
        p = pipe.pick(cx, cy)
        assert p is not None and p["source"] == "scanner"


def test_a_killed_map_stage_is_restarted_and_the_map_comes_back(tmp_path):
    """SIGKILL the map stage: the supervisor restarts it, the new one makes a new region, the
    render stage takes it (and resends its camera), the map is whole again; the live part
    never stopped; the dead stage's region file is gone."""
    import glob
    import signal

    las = write_las(str(tmp_path / "tile.las"), N_MAP, seed=3)
    live, live_pts = _live(str(tmp_path))
    with Pipeline.from_dict(_config(live, las), out_dir=str(tmp_path)) as pipe:
        render = lambda: pipe.stats()["stages"]["render"]  # noqa: E731
        pipe.wait(120, until=lambda: render().get("map_points", 0) >= N_MAP)
        m = pipe.stats()["stages"]["map"]
        old_region = glob.glob(os.path.join(pipe._sup.run_dir, f"map-region-{m['pid']}-*"))
        assert len(old_region) == 1
        os.kill(m["pid"], signal.SIGKILL)
        pipe.wait(120, until=lambda: pipe.stats()["stages"]["map"].get("restarts", 0) >= 1
                  and pipe.stats()["stages"]["map"].get("map_version") is not None
                  and pipe.stats()["accounting"].get("map_agrees") is True
                  and pipe.stats()["accounting"]["ingest_written"] == len(live_pts))
        st = pipe.stats()
        assert st["stages"]["map"]["restarts"] >= 1 and st["stages"]["map"]["pid"] != m["pid"]
        assert st["accounting"]["map_points_drawn"] == st["accounting"]["map_points_held"] == N_MAP
        assert not os.path.exists(old_region[0])
        assert st["accounting"]["ingest_written"] == len(live_pts)
        pipe.camera(eye=list(EYE), target=list(TARGET), up=UP, fov_deg=60.0)
        corner = ORIGIN + [60.0, 60.0, 0.0]
        p = pipe.pick(*_px(corner))
        assert p is not None and p["source"] == f"map: {las}"


@pytest.mark.parametrize("bad", ["map.path", "map.point_budget"])
def test_a_bad_map_block_is_refused_at_load_naming_the_key(tmp_path, bad):
    from pointflow.config import ConfigError, load_config

    live, _ = _live(str(tmp_path))
    cfg = _config(live, str(tmp_path / "missing.las"))
    if bad == "map.point_budget":
        cfg["map"]["path"] = write_las(str(tmp_path / "t.las"), 10)
        cfg["map"]["point_budget"] = 0
    with pytest.raises(ConfigError) as e:
        load_config(cfg)
    assert str(e.value).startswith(bad)


def test_a_copc_map_in_a_pipeline(tmp_path):
    """A COPC file (copc-lib's writer) is read through its own hierarchy: the whole map (budget
    above its points) reaches the renderer, coloured by intensity with the live points, and a
    pick names it."""
    pytest.importorskip("copclib", reason="copclib (copc-lib's COPC writer) comes with the test extra: pip install 'pointflow[test]'")
    from .mapfiles import write_copc

    copc = write_copc(str(tmp_path / "tile.copc.laz"), N_MAP, seed=5)
    live, live_pts = _live(str(tmp_path))
    cfg = _config(live, copc)
    cfg["render"]["color_by"] = "intensity"
    cfg["ring"]["extra_channels"] = ["intensity"]
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as pipe:
        # a view of the whole tile: every node is in it (the auto camera frames the 1st-99th
        # percentile box, and a node wholly outside the view is rightly not loaded)
        pipe.wait(60, until=lambda: pipe.stats()["stages"]["render"].get("map_points", 0) > 0)
        pipe.camera(eye=list(EYE), target=list(TARGET), up=UP, fov_deg=60.0)
        # what this view reaches in the file's hierarchy (a node whose parent is not in a COPC
        # hierarchy is not reached from the root; the test writer makes a few such nodes)
        from pointflow.map import open_map, select_nodes

        with open_map(copc) as m:
            cam = Camera(eye=EYE, target=TARGET, up=UP, fov_deg=60.0)
            reach = sum(m.node(k).count for k in select_nodes(m, cam.view_proj(W, H), (W, H), cam.eye, 1 << 40))
        assert reach > 0.99 * N_MAP
        pipe.wait(120, until=lambda: pipe.stats()["stages"]["render"].get("map_points", 0) >= reach
                  and pipe.stats()["accounting"].get("map_agrees") is True)
        st = pipe.stats()
        assert st["accounting"]["map_points_drawn"] == st["accounting"]["map_points_held"] == reach
        assert st["accounting"]["map_file_points"] == N_MAP
        p = pipe.pick(*_px(ORIGIN + [60.0, 60.0, 0.0]))
        assert p is not None and p["source"] == f"map: {copc}"
        assert "intensity" in p["channels"]
        truth = laspy_points(copc)
        i = int(np.argmin(np.linalg.norm(truth["positions"] - p["position"], axis=1)))
        assert np.linalg.norm(truth["positions"][i] - p["position"]) < 1e-9
        assert p["channels"]["intensity"] == float(truth["intensity"][i])


def test_a_source_may_not_take_the_map_stage_name(tmp_path):
    from pointflow.config import ConfigError, load_config

    live, _ = _live(str(tmp_path))
    cfg = _config(live, write_las(str(tmp_path / "t.las"), 10))
    cfg["source"]["name"] = "map"
    with pytest.raises(ConfigError) as e:
        load_config(cfg)
    assert str(e.value).startswith("sources[0].name")


def test_a_restarted_render_stage_gets_the_whole_map_again(tmp_path):
    """SIGKILL the render stage: its standby takes over (a renderer already sized for the ring
    and the map slots), says hello, and the map stage sends everything again."""
    import signal

    las = write_las(str(tmp_path / "tile.las"), N_MAP, seed=6)
    live, live_pts = _live(str(tmp_path))
    with Pipeline.from_dict(_config(live, las), out_dir=str(tmp_path)) as pipe:
        st = lambda: pipe.stats()["stages"]  # noqa: E731
        pipe.wait(120, until=lambda: st()["render"].get("map_points", 0) >= N_MAP)
        pid = st()["render"]["pid"]
        os.kill(pid, signal.SIGKILL)
        pipe.wait(120, until=lambda: st()["render"].get("restarts", 0) >= 1 and st()["render"]["pid"] != pid
                  and st()["render"].get("map_points", 0) >= N_MAP and pipe.stats()["accounting"].get("map_agrees"))
        s = pipe.stats()
        assert s["stages"]["render"]["restarts"] >= 1
        assert s["accounting"]["map_points_drawn"] == s["accounting"]["map_points_held"] == N_MAP
        pipe.camera(eye=list(EYE), target=list(TARGET), up=UP, fov_deg=60.0)
        p = pipe.pick(*_px(ORIGIN + [60.0, 60.0, 0.0]))
        assert p is not None and p["source"] == f"map: {las}"
        cx, cy = _px(live_pts.mean(axis=0))
        p = pipe.pick(cx, cy)
        assert p is not None and p["source"] == "scanner"


def test_a_pick_in_a_served_view_names_map_and_live_points(tmp_path):
    """A view of the view server (a DEALER on the render stage's views endpoint) picks a map
    point, named ``map: <file>`` at the file's exact position, and a live one, named by its
    source: the same answers as the main view's pick. The map's CRS is in feet (Oregon
    Lambert, EPSG:2992): the frames say so, for the grid, measures and height legend."""
    from view.test_views import ViewClient  # tests/ is on the path (rootdir)

    las = write_las(str(tmp_path / "tile.las"), N_MAP, seed=3, crs="EPSG:2992")
    live, live_pts = _live(str(tmp_path))
    truth = laspy_points(las)
    with Pipeline.from_dict(_config(live, las), out_dir=str(tmp_path)) as pipe:
        render = lambda: pipe.stats()["stages"]["render"]  # noqa: E731
        pipe.wait(120, until=lambda: render().get("map_points", 0) >= N_MAP and render()["points_in"] > 0)
        cl = ViewClient(pipe._sup.endpoints.views)
        try:
            cl.send(view="m", cmd="open", width=W, height=H, req=1)
            cl.send(view="m", cmd="camera", req=2, eye=list(EYE), target=list(TARGET), up=UP, fov_deg=60.0)
            r = cl.reply("m", 2)
            cl.send(view="m", cmd="credit", n=2)
            head = cl.frame("m", r["version"], timeout_s=120)[0]
            assert head["units"] == {"xy": "ft", "z": "ft"}, head.get("units")
            assert head["legend"]["color_by"] == "z" and head["legend"]["unit"] == "ft", head["legend"]
            mx, my = _px(ORIGIN + [60.0, 60.0, 0.0])
            cl.send(view="m", cmd="pick", x=float(mx), y=float(my), req=3)
            p = cl.reply("m", 3)
            assert p["source"] == f"map: {las}", p
            d = np.linalg.norm(truth["positions"] - p["point"]["position"], axis=1)
            assert d.min() < 1e-9, "the picked map point is one of the file's points, in float64"
            cx, cy = _px(live_pts.mean(axis=0))
            cl.send(view="m", cmd="pick", x=float(cx), y=float(cy), req=4)
            p = cl.reply("m", 4)
            assert p["source"] == "scanner", p
            assert np.min(np.linalg.norm(live_pts - p["point"]["position"], axis=1)) < 1e-3
            # the page's stats line counts points, not slots: the ring's 1,600 of its 4,000 and
            # the map's 20,000 of its 50,000 budget (it said 54,000)
            st = cl.wait(lambda: next((m for m in reversed(cl.msgs) if m.get("type") == "stats"), None),
                         60, "a stats message")
            assert st["points"] == len(live_pts) + N_MAP, st
        finally:
            cl.close()


@pytest.mark.parametrize("scale", [1, 257])
def test_map_colour_in_the_8_bit_range_of_16_bit_fields_is_drawn(tmp_path, scale):
    """Many LAS writers (the Autzen tile among them) store 0..255 in the 16-bit colour fields:
    the map draws them as they are, as the file source does (the map shifted them to black);
    colour using the 16-bit range is scaled down."""
    import laspy

    las_path = str(tmp_path / "rgb.las")
    las = laspy.read(write_las(las_path, N_MAP, seed=4))
    las.red, las.green, las.blue = (np.full(N_MAP, v * scale) for v in (200, 100, 50))
    las.write(las_path)
    live, _ = _live(str(tmp_path))
    cfg = _config(live, las_path)
    cfg["render"]["color_by"] = "rgb"
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as pipe:
        render = lambda: pipe.stats()["stages"]["render"]  # noqa: E731
        pipe.wait(120, until=lambda: render().get("map_points", 0) >= N_MAP and render()["points_in"] > 0)
        pipe.camera(eye=list(EYE), target=list(TARGET), up=UP, fov_deg=60.0)
        img = np.asarray(Image.open(pipe.save_frame(str(tmp_path / "rgb.png"))))[..., :3].astype(int)
    mx, my = _px(ORIGIN + [60.0, 60.0, 0.0])
    patch = img[my - 3:my + 4, mx - 3:mx + 4].reshape(-1, 3)
    drawn = patch[(patch != BG).any(axis=1)]
    assert len(drawn) and (np.abs(drawn - [200, 100, 50]) <= 1).all(), drawn[:5]
