"""Many views in one render stage (render/view/hub.py): a real pipeline, the real render stage,
and a Python zmq DEALER as the view server, speaking the view protocol (docs/views.md).

Scene (world metres): a dense 20 x 20 m plane with a step (z = 0 for x < 10, z = 3 above),
two sources (left and right half), seen through cameras the test sets."""
from __future__ import annotations

import json
import os
import sys
import time

import numpy as np
import pytest
import zmq
from PIL import Image

from pointflow import Pipeline

sys.path.insert(0, os.path.dirname(os.path.dirname(__file__)))

W, H = 160, 120
TOP = {"eye": [10.0, 10.0, 40.0], "target": [10.0, 10.0, 0.0], "up": [0.0, 1.0, 0.0], "fov_deg": 60.0}
SIDE = {"eye": [-30.0, 10.0, 5.0], "target": [10.0, 10.0, 0.0], "up": [0.0, 0.0, 1.0], "fov_deg": 60.0}
TIERS = {"cpu-reference": {"backend": "cpu", "raster": "reference"},
         "cpu-compute": {"backend": "cpu", "raster": "compute"},
         "wgpu": {"backend": "wgpu"}}


def _scene(path: str) -> list[str]:
    g = np.stack(np.meshgrid(np.arange(0, 20, 0.25), np.arange(0, 20, 0.25)), -1).reshape(-1, 2)
    z = np.where(g[:, 0] >= 10.0, 3.0, 0.0)
    out = []
    for name, m in (("left", g[:, 0] < 10.0), ("right", g[:, 0] >= 10.0)):
        f = os.path.join(path, f"{name}.npz")
        np.savez(f, x=g[m, 0], y=g[m, 1], z=z[m], intensity=np.arange(int(m.sum()), dtype=np.float32))
        out.append(f)
    return out


def _config(files: list[str], tier: str) -> dict:
    r = {"size": [W, H], "point_size": 2, "color_by": "intensity", "output": {"every_n_frames": 100000}}
    r.update(TIERS[tier])
    return {"sources": [{"transport": "file", "name": n, "options": {"path": f, "realtime": False}}
                        for n, f in zip(("left", "right"), files)],
            "ring": {"max_points": 20000}, "cadence": {"target_hz": 30}, "render": r}


class ViewClient:
    """What a view server does, in a few lines: a DEALER on the render stage's ROUTER."""

    def __init__(self, endpoint: str):
        self.ctx = zmq.Context()
        self.sock = self.ctx.socket(zmq.DEALER)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.connect(endpoint)
        self.frames: dict[str, list] = {}
        self.msgs: list[dict] = []

    def send(self, **msg) -> None:
        self.sock.send(json.dumps(msg).encode())

    def _pump(self, timeout_ms: int) -> bool:
        if not self.sock.poll(timeout_ms):
            return False
        hdr_b, payload = self.sock.recv_multipart()
        hdr = json.loads(hdr_b)
        if hdr["type"] == "frame":
            img = np.frombuffer(payload, np.uint8).reshape(hdr["height"], hdr["width"], 4)
            self.frames.setdefault(hdr["view"], []).append((hdr, img))
        else:
            self.msgs.append(hdr)
        return True

    def wait(self, pred, timeout_s: float = 60.0, what: str = "a message"):
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            got = pred()
            if got:
                return got
            self._pump(100)
        raise AssertionError(f"timed out waiting for {what}; got {[m.get('type') for m in self.msgs][-10:]}")

    def reply(self, view: str, req: int, timeout_s: float = 60.0) -> dict:
        return self.wait(lambda: next((m for m in self.msgs if m.get("view") == view and m.get("req") == req),
                                      None), timeout_s, f"the reply {req} of {view}")

    def frame(self, view: str, version: int = 0, timeout_s: float = 60.0):
        return self.wait(lambda: next((f for f in reversed(self.frames.get(view, []))
                                       if f[0]["version"] >= version), None), timeout_s,
                         f"a frame of {view} at version {version}")

    def drain(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self._pump(50)

    def close(self) -> None:
        self.sock.close(0)
        self.ctx.term()


def _loaded(pipe, n: int) -> None:
    pipe.wait(90, until=lambda: pipe.stats()["stages"]["render"].get("drawn_count", 0) >= n)
    assert pipe.stats()["stages"]["render"].get("drawn_count", 0) >= n, "the scene never reached the renderer"


@pytest.mark.parametrize("tier", sorted(TIERS))
def test_two_views_independent_cameras_credit_and_close(tmp_path, tier):
    if tier == "wgpu":
        from gpu_util import require_adapter

        require_adapter()
    files = _scene(str(tmp_path))
    n = 80 * 80
    with Pipeline.from_dict(_config(files, tier), out_dir=str(tmp_path)) as pipe:
        _loaded(pipe, n)
        st = pipe.camera(**{k: TOP[k] for k in ("eye", "target", "up", "fov_deg")})  # main: from above
        main = np.asarray(Image.open(pipe.save_frame(str(tmp_path / "main.png"))))
        cl = ViewClient(pipe._sup.endpoints.views)
        try:
            cl.send(view="a", cmd="open", width=W, height=H, req=1)
            cl.send(view="b", cmd="open", width=200, height=100, req=2)
            assert cl.reply("a", 1)["type"] == "reply" and cl.reply("b", 2)["type"] == "reply"
            ra = cl.send(view="a", cmd="camera", req=3, **TOP) or cl.reply("a", 3)
            rb = cl.send(view="b", cmd="camera", req=4, **SIDE) or cl.reply("b", 4)
            assert ra["camera"]["eye"] == TOP["eye"] and rb["camera"]["eye"] == SIDE["eye"]
            cl.send(view="a", cmd="credit", n=2)
            cl.send(view="b", cmd="credit", n=2)
            ha, ia = cl.frame("a", ra["version"])
            hb, ib = cl.frame("b", rb["version"])
            assert (ha["width"], ha["height"]) == (W, H) and ia.shape == (H, W, 4)
            assert (hb["width"], hb["height"]) == (200, 100) and ib.shape == (100, 200, 4)
            # each frame says the camera it was drawn with and its colour legend (the page's overlay)
            assert ha["camera"]["eye"] == TOP["eye"] and ha["camera"]["target"] == TOP["target"]
            assert hb["camera"]["eye"] == SIDE["eye"] and 0 < hb["camera"]["near"] < hb["camera"]["far"]
            lg = ha["legend"]
            assert lg["color_by"] == "intensity" and lg["colormap"] == "turbo" and lg["auto"], lg
            assert lg["range"][0] < lg["range"][1], lg
            # view a has main's camera and size: the very same pixels as main's saved frame
            if not np.array_equal(ia[..., :3], main[..., :3]): np.save("/tmp/dbg_ia.npy", ia); np.save("/tmp/dbg_main.npy", main); print("DBG", ha, st, pipe.stats()["stages"]["render"])
            assert np.array_equal(ia[..., :3], main[..., :3]), "a view with main's camera must draw main's picture"
            lit = lambda img: int(np.count_nonzero((img[..., :3].astype(int) - img[0, 0, :3]).any(-1)))
            assert lit(ia) > 1000 and lit(ib) > 200, (lit(ia), lit(ib))
            # b at a's size: still its own (side) camera, so another picture
            cl.send(view="b", cmd="resize", width=W, height=H, req=7)
            cl.reply("b", 7)
            cl.drain(0.5)
            nb = len(cl.frames["b"])
            cl.send(view="b", cmd="credit", n=2)
            cl.wait(lambda: len(cl.frames["b"]) > nb, what="b at a's size")
            hb2, ib2 = cl.frames["b"][-1]
            assert ib2.shape == (H, W, 4) and not np.array_equal(ib2[..., :3], ia[..., :3]), \
                "independent cameras must give different pictures"

            # credit used up: a change waits, counted, and shows once credit comes
            cl.drain(1.0)
            used = len(cl.frames["a"])
            cl.send(view="a", cmd="credit", n=0)
            cl.send(view="a", cmd="orbit", azimuth_deg=30.0, req=5)
            r5 = cl.reply("a", 5)
            cl.drain(1.5)
            assert len(cl.frames["a"]) == used, "a view without credit must get no frames"
            skipped = lambda: pipe.stats()["stages"]["render"]["views"]["a"]["skipped_no_credit"]
            pipe.wait(30, until=lambda: skipped() >= 1)
            assert skipped() >= 1
            cl.send(view="a", cmd="credit", n=1)
            h5, i5 = cl.frame("a", r5["version"])
            assert not np.array_equal(i5, ia), "the orbit must show"

            # the data is uploaded once: views draw from what main uploaded
            up = pipe.stats()["stages"]["render"]["view_uploaded_bytes"]
            if tier in ("cpu-compute", "wgpu"):  # (wgpu: one set of point buffers, DATA_SETS)
                assert up == 0, up

            # close b: gone (a command to it is refused), a goes on
            cl.send(view="b", cmd="close")
            cl.send(view="b", cmd="orbit", azimuth_deg=5.0, req=6)
            gone_before = pipe.stats()["stages"]["render"].get("view_gone_messages", 0)
            err = cl.reply("b", 6)
            assert err["type"] == "error" and err["key"] == "view" and "unknown view" in err["error"]
            # a message to a view gone is a race, not bad input: counted apart, not warned of
            assert pipe.wait(30, until=lambda: pipe.stats()["stages"]["render"].get("view_gone_messages", 0) > gone_before)
            cl.send(view="b", cmd="close", req=17)  # closed twice (a page gone, then its server stopping): no error
            cl.send(view="a", cmd="orbit", azimuth_deg=0.0, req=18)
            cl.reply("a", 18)  # (answered in order: the second close was taken before it)
            assert not [m for m in cl.msgs if m.get("view") == "b" and m.get("req") == 17]
            pipe.wait(30, until=lambda: pipe.stats()["stages"]["render"]["views_open"] == 1)
            s = pipe.stats()["stages"]["render"]
            assert s["views_open"] == 1 and "b" not in s["views"]
            assert pipe.running
        finally:
            cl.close()


def test_bad_messages_are_counted_and_not_fatal(tmp_path):
    files = _scene(str(tmp_path))
    with Pipeline.from_dict(_config(files, "cpu-compute"), out_dir=str(tmp_path)) as pipe:
        _loaded(pipe, 80 * 80)
        cl = ViewClient(pipe._sup.endpoints.views)
        try:
            cl.sock.send(b"\xff not json")
            cl.sock.send(b"[1, 2]")
            cl.sock.send_multipart([b"{}", b"two frames"])
            cl.send(view="x", cmd="open", width=5, height=100, req=1)       # too small
            cl.send(view="x", cmd="open", width=100, height=100, size=3, req=2)  # unknown argument
            cl.send(view="x", cmd="open", width=100, height=100, req=3)
            cl.send(view="x", cmd="credit", n=-1, req=4)
            cl.send(view="x", cmd="dance", req=5)
            cl.send(view="x", cmd="zoom", factor="big", req=6)
            cl.send(view="x", cmd="pick", x="a", y=1, req=7)
            cl.send(view=None, cmd="close", req=8)
            e1, e2 = cl.reply("x", 1), cl.reply("x", 2)
            assert e1["type"] == "error" and e1["key"] == "open.width", e1
            assert e2["type"] == "error" and e2["key"] == "open.size", e2
            assert cl.reply("x", 3)["type"] == "reply"
            keys = {r: cl.reply("x", r)["key"] for r in (4, 5, 6, 7)}
            assert keys == {4: "credit.n", 5: "cmd", 6: "zoom.factor", 7: "pick.x"}, keys
            # garbage that names no view is answered with view None
            cl.wait(lambda: sum(m["type"] == "error" and m["view"] is None for m in cl.msgs) >= 4, what="4 errors")
            cl.send(view="x", cmd="credit", n=2)
            h, img = cl.frame("x")
            assert img.shape == (100, 100, 4)
            bad = lambda: pipe.stats()["stages"]["render"]["drops"].get("bad_view_message", 0)
            pipe.wait(30, until=lambda: bad() >= 10)
            assert bad() >= 10, pipe.stats()["stages"]["render"]["drops"]
            assert pipe.running
        finally:
            cl.close()


def test_pick_in_a_view_names_the_source(tmp_path):
    files = _scene(str(tmp_path))
    with Pipeline.from_dict(_config(files, "cpu-compute"), out_dir=str(tmp_path)) as pipe:
        _loaded(pipe, 80 * 80)
        cl = ViewClient(pipe._sup.endpoints.views)
        try:
            cl.send(view="p", cmd="open", width=W, height=H, req=1)
            cl.send(view="p", cmd="camera", req=2, **TOP)
            r = cl.reply("p", 2)
            cl.send(view="p", cmd="credit", n=2)
            cl.frame("p", r["version"])
            from pointflow.render.camera import Camera, project_to_pixels

            cam = Camera(eye=TOP["eye"], target=TOP["target"], up=TOP["up"], fov_deg=60.0)
            for world, name in (([5.0, 10.0, 0.0], "left"), ([15.0, 10.0, 3.0], "right")):
                px, py, _, _ = project_to_pixels(np.asarray([world]), cam.view_proj(W, H), W, H)
                req = 10 if name == "left" else 11
                cl.send(view="p", cmd="pick", x=float(px[0]), y=float(py[0]), req=req)
                p = cl.reply("p", req)
                assert p["type"] == "pick" and p["source"] == name, p
                assert np.allclose(p["point"]["position"], world, atol=0.5), p["point"]
            cl.send(view="p", cmd="pick", x=1.0, y=1.0, req=12)  # a corner: nothing there
            p = cl.reply("p", 12)
            assert p["point"] is None and p["source"] is None
        finally:
            cl.close()
        # each view frame is a "view_draw" slice of the profile trace
        from pointflow.profiling.report import write_profile

        stats = pipe.stop()
        write_profile(str(tmp_path / "prof"), pipe.collector, stats)
        doc = json.loads((tmp_path / "prof" / "trace.json").read_text())
        assert any(e.get("name") == "view_draw" for e in doc["traceEvents"])


def _stream_config(tier: str) -> dict:
    r = {"size": [W, H], "point_size": 2, "color_by": "intensity", "output": {"every_n_frames": 100000}}
    r.update(TIERS[tier])
    return {"sources": [{"transport": "api", "name": "api"}], "ring": {"max_points": 20000},
            "cadence": {"target_hz": 30}, "render": r}


def _batches():
    g = np.stack(np.meshgrid(np.arange(0, 20, 0.25), np.arange(0, 20, 0.25)), -1).reshape(-1, 2)
    pts = np.column_stack([g, np.where(g[:, 0] >= 10.0, 3.0, 0.0)]).astype(np.float32)
    return [(pts[i:i + 640], np.arange(i, i + 640, dtype=np.float32)) for i in range(0, len(pts), 640)]


def test_data_no_one_drew_while_main_rests_reaches_the_view_later(tmp_path):
    """Main rests while a view is open (drawn every 0.5 s), and the view takes no frames:
    the handoffs nobody drew carry their dirty ranges to the next draw. The picture at the
    end must be the one a run without views draws (nothing lost)."""
    pics = []
    for with_view in (True, False):
        with Pipeline.from_dict(_stream_config("cpu-compute"), out_dir=str(tmp_path)) as pipe:
            cl = ViewClient(pipe._sup.endpoints.views) if with_view else None
            try:
                if cl:
                    cl.send(view="s", cmd="open", width=W, height=H, req=1)
                    cl.send(view="s", cmd="camera", req=2, **TOP)
                    cl.reply("s", 2)
                for pos, inten in _batches():
                    pipe.send(pos, source="api", intensity=inten)
                    if cl:  # a client that takes no frames: main rests, nobody draws most handoffs
                        cl.drain(0.1)
                    else:
                        time.sleep(0.1)
                pipe.wait(60, until=lambda: pipe.stats()["accounting"]["ring_written"] >= 6400)
                if cl:
                    time.sleep(1.0)  # the last handoffs
                    cl.send(view="s", cmd="credit", n=0)
                    cl.drain(0.5)
                    cl.send(view="s", cmd="zoom", factor=1.0, req=3)  # a no-op: the version stays
                    cl.send(view="s", cmd="orbit", azimuth_deg=0.0, req=4)
                    r = cl.reply("s", 4)
                    cl.send(view="s", cmd="credit", n=1)
                    h, img = cl.frame("s", r["version"])
                    pics.append(img[..., :3].copy())
                else:
                    pipe.camera(**{k: TOP[k] for k in ("eye", "target", "up", "fov_deg")})
                    time.sleep(1.0)
                    pics.append(np.asarray(Image.open(pipe.save_frame(str(tmp_path / "ref.png"))))[..., :3])
            finally:
                if cl:
                    cl.close()
    assert np.array_equal(pics[0], pics[1]), \
        f"{int((pics[0] != pics[1]).any(-1).sum())} pixels differ from a run without views"


def test_a_restarted_render_stage_asks_for_its_views_again(tmp_path):
    """The render stage dies (SIGKILL) and its standby takes over: it knows no views, says
    ``unknown view`` to the first message of one, and the client's open brings it back."""
    import signal

    files = _scene(str(tmp_path))
    with Pipeline.from_dict(_config(files, "cpu-compute"), out_dir=str(tmp_path)) as pipe:
        _loaded(pipe, 80 * 80)
        cl = ViewClient(pipe._sup.endpoints.views)
        try:
            cl.send(view="r", cmd="open", width=W, height=H, req=1)
            cl.send(view="r", cmd="credit", n=2)
            cl.frame("r")
            pid = pipe.stats()["stages"]["render"]["pid"]
            os.kill(pid, signal.SIGKILL)
            pipe.wait(90, until=lambda: pipe.stats()["stages"]["render"].get("pid") not in (None, pid)
                      and pipe.stats()["stages"]["render"].get("restarts", 0) >= 1)
            err = None
            for i in range(120):  # until the new stage answers (its ROUTER is bound anew)
                cl.send(view="r", cmd="view_state", req=100 + i)
                cl.drain(0.5)
                err = next((m for m in cl.msgs if m.get("req", 0) >= 100 and m["type"] == "error"), None)
                if err:
                    break
            assert err is not None and err["key"] == "view" and "unknown view" in err["error"], cl.msgs[-3:]
            n = len(cl.frames["r"])
            cl.send(view="r", cmd="open", width=W, height=H, req=2)
            cl.send(view="r", cmd="credit", n=2)
            cl.wait(lambda: len(cl.frames["r"]) > n, what="a frame from the new render stage")
            assert pipe.running
        finally:
            cl.close()
