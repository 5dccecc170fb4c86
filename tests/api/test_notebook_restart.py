"""The notebook widget after a render restart (issue 40, item 3, for the notebook's view):
a restarted render stage numbers a reopened view's frames from 1 and has lost its camera;
the widget opens its view again with the camera it had and a frame number past every frame
it saw, so frames go on (numbered past the old ones) and the view stays where the user turned it.

Under load: every wait is on a condition (frames counted, the restart seen in stats), with
bounds far above what a loaded 2-core machine needs; nothing is timed."""
from __future__ import annotations

import os
import signal

import numpy as np
import pytest

from pointflow import Pipeline

from .helpers import api_config, until

pytest.importorskip("anywidget", reason="the notebook extra comes with the test extra: pip install 'pointflow[test]'")


def test_the_widget_reopens_its_view_with_its_camera_after_a_render_restart(tmp_path):
    from pointflow.notebook.widget import LiveView

    cfg = api_config()
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as p:
        p.send(np.random.default_rng(1).normal(size=(5000, 3)).astype(np.float32),
               intensity=np.ones(5000, np.float32))
        view = LiveView(p, width=96, height=64)
        sent: list[int] = []
        view.send = lambda content, buffers=None: (sent.append(content["seq"]) if content.get("type") == "frame"
                                                   else None)
        acked: set = set()

        def frames_past(n: int):
            for seq in [s for s in sent if s not in acked]:  # the browser draws and acks each frame
                acked.add(seq)
                view._inbox.put({"type": "ack", "seq": seq})
            return len(sent) >= n

        until(lambda: frames_past(1), 120, "a first frame")
        view._inbox.put({"type": "control", "msg": {"cmd": "orbit", "azimuth_deg": 35, "elevation_deg": 15}})
        until(lambda: frames_past(0) and view.last_reply and view.last_reply.get("camera", {}).get("mode") == "fixed",
               60, "the orbit's reply")
        eye = view.last_reply["camera"]["eye"]
        before = max(sent)
        render = p.stats()["stages"]["render"]
        os.kill(render["pid"], signal.SIGKILL)
        until(lambda: frames_past(0) and view.views_reopened >= 1, 120, "the view opened again")
        # the new stage draws the reopened view once (the data does not change after that)
        until(lambda: frames_past(0) and max(sent) > before, 120, "a frame from the new render stage")
        assert all(b > a for a, b in zip(sent, sent[1:])), "frame numbers went back after the restart"
        view._inbox.put({"type": "control", "msg": {"cmd": "view_state"}})
        view.last_reply = None
        after = until(lambda: frames_past(0) and view.last_reply, 60, "the view state")
        assert after["camera"]["mode"] == "fixed" and after["camera"]["eye"] == pytest.approx(eye)
        view.close()
