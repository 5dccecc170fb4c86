"""A cadence frozen (SIGSTOP) and replaced as hung must not leave the renderer without
frames (issue 19's chaos soak: after a 3-s cadence freeze the renderer drew nothing for
75 s, through a second cadence restart, until the renderer itself was restarted).

The slab headers record which slabs the cadence handed out; a restarted cadence starts
from them. The renderer's releases sent while the cadence was frozen die with it, so the
new cadence believed the renderer still held both slabs and skipped every tick
(``renderer_busy``) until a renderer restart said hello."""
from __future__ import annotations

import os
import signal

from pointflow import Pipeline

from ..helpers import assert_gone, assert_segments_gone, small_config, wait_for


def _cadence(pipe) -> dict:
    return pipe.stats()["stages"]["cadence"]


def test_frames_resume_after_a_frozen_cadence_is_replaced(tmp_path):
    """A cadence frozen with both slabs out is replaced and frames resume, without a
    renderer restart. On a loaded machine the same holds: the frozen cadence is hung at
    once (its threads are stopped), the healthy stages are not (starved is not hung); only
    the waits (120 s) and the margin of the renderer's own freeze change."""
    # hung_after_ms 5000: the renderer's own 0.8-s freeze below is not a hang, even when this
    # (starved) test process sends its SIGCONT seconds late. Without latest_only the cadence
    # fills the second slab while the renderer draws the first; with it, only when a frame
    # runs past its stall limit (seconds, on a loaded machine)
    cfg = small_config(supervisor={"max_restarts": 3, "hung_after_ms": 5000, "restart_backoff_ms": 50,
                                   "standby": False},
                       cadence={"target_hz": 30, "latest_only": False})
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as pipe:
        assert wait_for(lambda: pipe.stats()["frames"] >= 5, 120)
        render_pid, cad_pid = pipe.stats()["stages"]["render"]["pid"], _cadence(pipe)["pid"]
        pids = [v["pid"] for v in pipe.stats()["stages"].values()]
        # 1. The renderer stalls: the cadence hands out its second slab too, so both are out.
        os.kill(render_pid, signal.SIGSTOP)
        try:
            wait_for(lambda: False, 0.8)
        finally:
            # 2. The cadence freezes with both slabs out; the renderer comes back, draws the
            #    newest handoff and releases both, into the frozen cadence's socket.
            os.kill(cad_pid, signal.SIGSTOP)
            os.kill(render_pid, signal.SIGCONT)
        try:
            # 3. The supervisor replaces the frozen cadence (SIGKILL: the releases are lost).
            assert wait_for(lambda: _cadence(pipe)["pid"] != cad_pid and _cadence(pipe)["ready"], 120), \
                pipe.stats()["events"]
        finally:
            try:
                os.kill(cad_pid, signal.SIGCONT)
            except ProcessLookupError:
                pass
        frames = pipe.stats()["frames"]
        # 4. Frames keep coming from the new cadence.
        resumed = wait_for(lambda: pipe.stats()["frames"] >= frames + 5, 120)
        st = pipe.stats()
    cad = st["stages"]["cadence"]
    assert resumed, (f"renderer drew {st['frames'] - frames} frames in 120 s after the cadence was replaced; "
                     f"cadence skipped {cad.get('skipped')}")
    assert st["stages"]["render"]["restarts"] == 0  # not rescued by a renderer restart
    assert [e["stage"] for e in st["events"]] == ["cadence"], st["events"]
    assert cad.get("renderer_resyncs", 0) >= 1, cad
    assert_segments_gone(st)
    assert_gone(pids + [cad["pid"]])
