"""The notebook widget's kernel side with a real pipeline (no browser): the timeline's requests
reach the replaying source through ``Pipeline.playback`` (a seek answered once it has landed),
malformed ones are refused naming the argument, and the widget learns that the pipeline
stopped (``LiveView.stopped``). The browser half: tests/notebook/test_widget_controls.py."""
from __future__ import annotations


import numpy as np
import pytest

from pointflow import Pipeline

from .helpers import until

pytest.importorskip("anywidget", reason="the notebook extra comes with the test extra: pip install 'pointflow[test]'")


def test_timeline_requests_refusals_and_the_stopped_state(tmp_path):
    from pointflow.notebook.widget import LiveView

    scans = tmp_path / "scans"
    scans.mkdir()
    for i in range(10):  # message i at i / 2 s
        np.savez(scans / f"s{i:03d}.npz", x=np.full(50, float(i)), y=np.arange(50.0), z=np.zeros(50))
    cfg = {"source": {"transport": "file", "name": "rec", "options": {"path": str(scans), "rate": 2}},
           "playback": {"paused": True, "hold": True}, "tracing": {"enabled": False},
           "render": {"backend": "cpu", "size": [64, 48], "output": {"dir": None}}}
    p = Pipeline.from_dict(cfg, out_dir=str(tmp_path)).start()
    try:
        view = LiveView(p, width=64, height=48)
        assert view.replays == ["rec"] and view.stopped == ""
        got: list[dict] = []
        view.send = lambda content, buffers=None: got.append(content)

        def answer(req: int) -> dict:
            return until(lambda: next((m for m in got if m.get("req") == req and m["type"] in ("playback", "error")),
                                       None), 60, f"the answer to request {req}")

        view._inbox.put({"type": "playback", "req": 1, "args": {"seek_fraction": 0.8}})
        st = answer(1)["sources"]["rec"]
        assert st["index"] == 8 and st["position_s"] == pytest.approx(4.0) and st["paused"]
        for req, args, key in [(2, {"seek_s": "far"}, "playback.seek_s"), (3, {"rewind": True}, "playback.rewind"),
                               (4, {"rate": -1}, "playback.rate"), (5, [1, 2], "playback.args"),
                               (6, {"step": 0.5}, "playback.step")]:
            m = {"type": "playback", "req": req, "args": args}
            view._inbox.put(m)
            rep = answer(req)
            assert rep["type"] == "error" and rep["key"] == key and rep["error"], rep
        assert view.playback_refused == 5
        assert p.playback()["rec"]["index"] == 8  # the replay goes on as it was
        assert view.stopped == ""
        p.stop()
        until(lambda: view.stopped, 30, "the widget to see the pipeline stop")
        assert view.stopped == "run ended"
        view.close()
    finally:
        p.stop()
