"""The source stage in a real process: stamping, end of stream, HWM never blocks forever."""
import json
import multiprocessing as mp
import os
import shutil
import time

import zmq

from pointflow import wire
from pointflow.config import load_config, new_run_dir
from pointflow.runtime.stage import stage_main
from pointflow.stage.context import RunInfo


def _start(cfg):
    c = load_config(cfg)
    run_dir = new_run_dir()
    ep = c.resolved_endpoints(run_dir)
    z = zmq.Context()
    control = z.socket(zmq.PULL)
    control.bind(ep.control)
    trace = z.socket(zmq.PULL)
    trace.bind(ep.trace)
    info = RunInfo(run_dir=run_dir, endpoints=ep, ring_name="", slab_names=("", ""), out_dir=None,
                   supervisor_pid=os.getpid(), source_index=0)
    p = mp.get_context("spawn").Process(target=stage_main, args=("src", "source", cfg, os.getcwd(), info), daemon=True)
    p.start()
    return p, z, control, trace, ep, run_dir


def _until_done(p, control, timeout=60.0, on_idle=None):
    """Control messages until the stage says its input ended ("done"); it then stays up,
    connected (so nothing queued for ingest is lost), until it is stopped: stop it."""
    msgs, end = [], time.monotonic() + timeout
    while time.monotonic() < end and not any(m["type"] == "done" for m in msgs):
        msgs += _messages(control, 0.05)
        if on_idle is not None:
            on_idle()
    assert any(m["type"] == "done" for m in msgs), "the stage never said its input ended"
    time.sleep(0.3)
    assert p.is_alive(), "a finished source stays connected until it is stopped"
    p.terminate()  # SIGTERM: the stage's stop
    p.join(30)
    return msgs + _messages(control)


def _messages(control, timeout=0.2):
    out = []
    while control.poll(int(timeout * 1000)):
        out.append(json.loads(control.recv()))
        timeout = 0.01
    return out


def test_source_stamps_chunks_and_reports_done():
    cfg = {"source": {"transport": "synthetic", "options": {"scans": 2, "realtime": False, "points_per_scan": 5000}}}
    p, z, control, trace, ep, run_dir = _start(cfg)
    pull = z.socket(zmq.PULL)
    pull.bind(ep.ingest)
    try:
        chunks = []
        end = time.monotonic() + 60
        while len(chunks) < 20 and time.monotonic() < end:
            if pull.poll(100):
                chunks.append(wire.decode(pull.recv_multipart()))
        msgs = _until_done(p, control)
        assert [c.seq for c in chunks] == list(range(20))
        assert all(c.source_id == "source" and c.trace_id and c.t_sent_ns for c in chunks)
        assert len({c.trace_id for c in chunks}) == 20
        assert p.exitcode == 0 and any(m["type"] == "done" for m in msgs)
        last = [m for m in msgs if m["type"] == "heartbeat"][-1]["stats"]
        assert last["points_out"] == sum(c.n for c in chunks) and last["transport_scans"] == 2
    finally:
        for s in (pull, control, trace):
            s.close(linger=0)
        z.term()
        shutil.rmtree(run_dir, ignore_errors=True)


def test_live_source_drops_at_hwm_and_still_stops_promptly():
    # nobody reads the ingest endpoint: the live source must drop (counted), not block
    cfg = {"source": {"transport": "synthetic",
                      "options": {"realtime": True, "rate": 50, "points_per_scan": 2000, "chunks_per_scan": 50}}}
    p, z, control, trace, ep, run_dir = _start(cfg)
    try:
        end = time.monotonic() + 60
        drops = 0
        while time.monotonic() < end and not drops:
            for m in _messages(control, 0.2):
                if m["type"] == "heartbeat":
                    drops = m["stats"]["drops"].get("hwm", 0)
        assert drops > 0
        t0 = time.monotonic()
        p.terminate()
        p.join(10)
        assert p.exitcode == 0 and time.monotonic() - t0 < 10
    finally:
        if p.is_alive():
            p.kill()
        for s in (control, trace):
            s.close(linger=0)
        z.term()
        shutil.rmtree(run_dir, ignore_errors=True)
