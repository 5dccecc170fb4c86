"""The cadence as a real stage process (spawned like the supervisor does), with this test
playing supervisor (control + trace endpoints) and renderer (SlabReader)."""
import json
import multiprocessing as mp
import os
import signal
import time

import numpy as np
import pytest
import zmq

from pointflow.cadence.messages import encode_hello
from pointflow.config import load_config
from pointflow.profiling.collector import SpanCollector
from pointflow.ring import PointRing, SlabPair, SlabReader
from pointflow.runtime.stage import stage_main
from pointflow.stage.context import RunInfo

from .conftest import assert_unlinked


@pytest.fixture
def world(tmp_path):
    cfg = load_config({"source": {"transport": "synthetic"}, "cadence": {"target_hz": 50},
                       "policy": {"tier": "L", "mode": "eco"}, "ring": {"max_points": 100_000},
                       "tracing": {"flush_ms": 20}})
    eps = cfg.resolved_endpoints(str(tmp_path))
    ring = PointRing(100_000, channels=cfg.ring_channels())
    slabs = SlabPair.create(ring.layout)
    z = zmq.Context()
    control = z.socket(zmq.PULL); control.bind(eps.control)
    coll = SpanCollector(z, eps.trace)
    frames = z.socket(zmq.PULL); frames.bind(eps.frames)
    release = z.socket(zmq.PUSH); release.connect(eps.release)
    reader = SlabReader(slabs, frames, release)
    procs = []

    def start(restart_count=0):
        info = RunInfo(run_dir=str(tmp_path), endpoints=eps, ring_name=ring.name, slab_names=tuple(slabs.names),
                       out_dir=None, supervisor_pid=os.getpid(), restart_count=restart_count)
        p = mp.get_context("spawn").Process(target=stage_main, args=("cadence", "cadence", cfg.to_dict(),
                                                                     cfg.base_dir, info), daemon=True)
        p.start()
        procs.append(p)
        return p

    class W:
        pass

    w = W()
    w.__dict__.update(cfg=cfg, ring=ring, slabs=slabs, control=control, coll=coll, reader=reader,
                      release=release, start=start)
    yield w
    for p in procs:
        if p.is_alive():
            p.kill()
        p.join(5)
    for s in (control, frames, release):
        s.close(0)
    coll.close()
    z.term()
    names = (ring.name, *slabs.names)
    slabs.close(); slabs.unlink()
    ring.close(); ring.unlink()
    assert_unlinked(*names)


def recv_handoffs(w, n, timeout=60.0):
    out = []
    end = time.monotonic() + timeout
    while len(out) < n and time.monotonic() < end:
        got = w.reader.recv(100)
        if got:
            out.append(got[0])
            w.reader.release()
    assert len(out) >= n, f"only {len(out)} handoffs in {timeout}s"
    return out


def last_heartbeat(w, timeout=60.0):
    """The first heartbeat that has seen 20 ticks and 5 handoffs (or the last one at the
    timeout). Not the first one followed by a quiet 100 ms: on a loaded machine that can be
    a heartbeat queued before the handoffs the test already received."""
    hb = None
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if w.control.poll(100):
            m = json.loads(w.control.recv())
            if m["type"] == "heartbeat" and m["stats"].get("ticks"):
                hb = m
                if hb["stats"]["ticks"] > 20 and hb["stats"].get("published", 0) >= 5:
                    return hb
    return hb


def test_cadence_process_ticks_hands_off_traces_and_restarts(world):
    """On a loaded machine the same handoffs, heartbeat and restart hold; a cadence process
    can take many seconds to start there, so every wait is up to 60 s (nothing timed)."""
    w = world
    p = w.start()
    w.ring.push(np.random.rand(500, 3).astype(np.float32), trace_id=0xABC)
    time.sleep(1.0)
    assert w.reader.recv(0) is None  # a first cadence waits for the renderer's hello
    w.release.send_multipart(encode_hello(os.getpid(), 0))
    hs = recv_handoffs(w, 5)
    assert 0xABC in [t for h in hs for t in h.trace_ids]
    assert all(h.extra["budget"] == 80_000 for h in hs)       # L eco
    assert hs[-1].count == 500
    hb = last_heartbeat(w)
    st = hb["stats"]
    assert st["target_hz"] == 50 and st["published"] >= 5
    assert st["policy"]["tier"] == "L" and st["policy"]["point_budget"] == 80_000
    assert st["jitter_ms"]["p99"] is not None
    # spans reach the collector
    end = time.monotonic() + 60
    while time.monotonic() < end:
        w.coll.poll(100)
        t = w.coll.table()
        if len(t) and 0xABC in t.trace_id.tolist():
            break
    t = w.coll.table()
    assert t.event_names[int(t.event[t.trace_id.tolist().index(0xABC)])] == "cadence_snapshot"

    # a new renderer says hello -> full handoff next
    w.release.send_multipart(encode_hello(os.getpid(), 1))
    hs = recv_handoffs(w, 3)
    assert any(h.dirty is None for h in hs)

    # SIGKILL the cadence; a restarted one resumes from the slab headers (seq keeps rising)
    last_seq = hs[-1].seq
    os.kill(p.pid, signal.SIGKILL)
    p.join(5)
    p2 = w.start(restart_count=1)
    w.ring.push(np.random.rand(100, 3).astype(np.float32), trace_id=0xDEF)
    hs = recv_handoffs(w, 3)
    assert hs[0].seq > last_seq and hs[0].dirty is None      # first handoff after restart is full
    assert 0xDEF in [t for h in hs for t in h.trace_ids]
    assert hs[-1].count == 600

    p2.terminate()                                            # SIGTERM: clean exit
    p2.join(10)
    assert p2.exitcode == 0


def _slab_is_ring(w, slab):
    src, dst = w.ring.arrays, w.slabs.arrays(slab)
    return all(np.array_equal(dst[k], a, equal_nan=True) for k, a in src.items())  # unwritten channel slots are NaN


def test_a_cadence_process_fills_the_next_slab_while_the_renderer_draws(world):
    """While the renderer holds its slab (a slow frame), the cadence process copies what
    ingest commits into the other slab and hands nothing out; when the frame is reported
    done, the next handoff is that slab, showing the ring as it is, and carries the chunks
    committed during the frame."""
    from pointflow.cadence.messages import encode_frame_time

    w = world
    p = w.start()
    w.release.send_multipart(encode_hello(os.getpid(), 0))
    w.ring.push(np.random.rand(1000, 3).astype(np.float32), trace_id=1)
    got = None
    end = time.monotonic() + 10
    while got is None and time.monotonic() < end:
        got = w.reader.recv(100)
    assert got is not None, "no first handoff"
    h1 = got[0]                                   # the renderer "draws" h1: holds its slab
    while 1 not in h1.trace_ids:                  # (a handoff may have gone out before the push)
        w.reader.release()
        w.release.send_multipart(encode_frame_time(10.0, h1.seq))
        got = w.reader.recv(5000)
        assert got is not None, "chunk 1 never handed out"
        h1 = got[0]
    nxt = 1 - h1.slab
    w.ring.push(np.random.rand(30_000, 3).astype(np.float32), trace_id=2)
    end = time.monotonic() + 10
    while not _slab_is_ring(w, nxt) and time.monotonic() < end:
        time.sleep(0.05)
    assert _slab_is_ring(w, nxt), "the next slab was not filled while the renderer drew"
    assert w.reader.recv(200) is None             # latest_only: nothing handed out mid-frame
    w.reader.release()
    w.release.send_multipart(encode_frame_time(500.0, h1.seq))   # the frame is done
    got = w.reader.recv(10_000)
    assert got is not None, "no handoff after the frame report"
    h2, view = got
    assert h2.slab == nxt and h2.seq > h1.seq
    assert h2.trace_ids == [2] and h2.count == 31_000
    assert _slab_is_ring(w, nxt)
    prefilled = 0
    end = time.monotonic() + 10
    while prefilled < 30_000 and time.monotonic() < end:   # heartbeats come every few 100 ms
        if w.control.poll(100):
            m = json.loads(w.control.recv())
            if m["type"] == "heartbeat":
                prefilled = m["stats"].get("prefilled_slots", 0)
    assert prefilled >= 30_000
    p.terminate()
    p.join(10)
    assert p.exitcode == 0
