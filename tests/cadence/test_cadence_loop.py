"""The Cadence tick loop against a real ring, real slabs and real ZeroMQ sockets.

Time comes from a fake clock (ticks are driven with ``ticker.poll()`` after advancing it), so
skips, lateness and the adaptive interval are tested without timing flakiness.
"""
import os
import time

import numpy as np
import pytest
import zmq

from pointflow.cadence.messages import CONTROL_TAG, encode_frame_time, encode_hello, encode_idle
from pointflow.cadence.policy import resolve_policy
from pointflow.cadence.process import Cadence
from pointflow.config import load_config
from pointflow.profiling.collector import SpanCollector
from pointflow.profiling.spans import SpanEmitter
from pointflow.ring import PointRing, SlabPair, SlabReader

from .conftest import assert_unlinked
from .fakeclock import FakeClock


class Rig:
    def __init__(self, tmp, cfg_over=None, bind_renderer=True, latest_only=True):
        d = {"source": {"transport": "synthetic"}, "cadence": {"target_hz": 100},
             "policy": {"tier": "M"}, "render": {"size": [320, 240]}, "ring": {"max_points": 5000}}
        for k, v in (cfg_over or {}).items():
            d.setdefault(k, {}).update(v)
        self.cfg = load_config(d)
        self.ring = PointRing(5000, channels=["intensity"])
        self.slabs = SlabPair.create(self.ring.layout)
        self.z = zmq.Context()
        ep_f, ep_r = f"ipc://{tmp}/f.sock", f"ipc://{tmp}/r.sock"
        self.rel = self.z.socket(zmq.PULL); self.rel.bind(ep_r)
        self.rpush = self.z.socket(zmq.PUSH); self.rpush.connect(ep_r)
        self.rpull = None
        if bind_renderer:
            self.rpull = self.z.socket(zmq.PULL); self.rpull.bind(ep_f)
            self.reader = SlabReader(self.slabs, self.rpull, self.rpush)
        self.ready = self.z.socket(zmq.PUSH); self.ready.setsockopt(zmq.IMMEDIATE, 1)
        self.ready.connect(ep_f)
        self.coll = SpanCollector(self.z, "inproc://spans")
        self.spans = SpanEmitter(self.z, "inproc://spans", "cadence", batch=10_000)
        self.clk = FakeClock()
        self.decision = resolve_policy(self.cfg, probe_gpu=False)
        self.cad = Cadence(self.ring, self.slabs, self.ready, self.rel, self.z, self.cfg, self.decision,
                           spans=self.spans, clock=self.clk, sleep=self.clk.sleep, latest_only=latest_only)
        time.sleep(0.05)  # let ipc connections establish

    def tick(self, advance=None):
        self.clk.advance(self.cad.ticker.interval_s if advance is None else advance)
        tk = self.cad.ticker.poll()
        assert tk is not None
        return self.cad.serve(tk)

    def recv(self):
        got = self.reader.recv(1000)
        assert got is not None, "no handoff arrived"
        return got

    def release(self):
        """Renderer releases its slab; wait until the cadence has seen it."""
        seq = self.reader._held[1] if self.reader._held else None
        self.reader.release()
        deadline = time.monotonic() + 2
        while seq is not None and self.cad.done_seq < seq and time.monotonic() < deadline:
            self.cad.drain(0.01)
        assert seq is None or self.cad.done_seq >= seq, "release did not arrive"

    def send(self, frames):
        self.rpush.send_multipart(frames)
        deadline = time.monotonic() + 2
        while time.monotonic() < deadline:  # wait until the cadence has taken it
            if self.rel.poll(10):
                self.cad.drain(0)
                return
        raise AssertionError("message did not arrive")

    def push(self, n, tid):
        self.ring.push(np.random.rand(n, 3).astype(np.float32), trace_id=tid,
                       intensity=np.full(n, tid, np.float32))

    def close(self):
        self.cad.close()
        self.spans.close()
        self.coll.close()
        for s in (self.rel, self.ready, self.rpush, self.rpull):
            if s is not None:
                s.close(0)
        self.z.term()
        names = (self.ring.name, *self.slabs.names)
        self.slabs.close(); self.slabs.unlink()
        self.ring.close(); self.ring.unlink()
        assert_unlinked(*names)


@pytest.fixture
def rig(tmp_path):
    r = Rig(tmp_path)
    yield r
    r.close()


def test_publishes_budget_and_spans_for_new_trace_ids_once(rig):
    rig.push(100, 11)
    rig.push(50, 12)
    h = rig.tick()
    assert h and h.extra["budget"] == rig.decision.point_budget == min(350_000, 4 * 320 * 240, 5000)
    got, view = rig.recv()
    assert got.seq == h.seq and sorted(got.trace_ids) == [11, 12] and view.size == 150
    rig.release()
    rig.push(10, 13)
    h2 = rig.tick()
    assert h2.trace_ids == [13]
    rig.recv()
    rig.spans.flush()
    time.sleep(0.05)
    rig.coll.poll(0)
    t = rig.coll.table()
    snap = t.event == t.event_names.index("cadence_snapshot")
    assert sorted(t.trace_id[snap].tolist()) == [11, 12, 13]  # each trace id once, when first visible
    assert rig.cad.stats()["published"] == 2


def test_skips_when_renderer_holds_both_slabs_no_backlog(tmp_path):
    rig = Rig(tmp_path, latest_only=False)
    try:
        _both_slabs(rig)
    finally:
        rig.close()


def _both_slabs(rig):
    rig.push(10, 1)
    assert rig.tick()            # slab A -> renderer takes it
    rig.recv()
    assert rig.tick()            # slab B handed out, renderer not reading yet
    for _ in range(5):
        assert rig.tick() is False
    st = rig.cad.stats()
    assert st["skipped"] == {"renderer_busy": 5} and st["published"] == 2
    got, _ = rig.recv()          # renderer takes B and releases A
    assert got.seq == 2          # only one handoff was waiting: no backlog built up
    time.sleep(0.05)
    h = rig.tick()
    assert h and h.seq == 3


def test_latest_only_waits_for_the_renderer_then_sends_fresh_data(rig):
    rig.push(10, 1)
    h1 = rig.tick()
    got, _ = rig.recv()                       # renderer draws slab A (holds it)
    rig.push(10, 2)
    for _ in range(3):                        # a queued second slab would go stale: skip
        assert rig.tick() is False
    assert rig.cad.stats()["skipped"] == {"renderer_pending": 3}
    rig.push(10, 3)
    rig.release()                             # frame done
    rig.send(encode_frame_time(30.0, h1.seq))
    h2 = rig.tick()
    assert h2 and sorted(h2.trace_ids) == [2, 3]   # the newest data, sent when the renderer is ready
    rig.recv()
    # a renderer that never releases does not starve: after STALL_S it gets data anyway
    from pointflow.cadence.process import STALL_S

    rig.push(10, 4)
    assert rig.tick() is False
    assert rig.cad.stall_s == STALL_S                    # 10 x 30 ms frames < STALL_S
    h3 = rig.tick(advance=STALL_S + 0.01)
    assert h3 and h3.trace_ids == [4]
    # a slow renderer (frames of 800 ms) is given 10 frame times before the cadence gives up
    rig.recv()                      # takes h3, releasing h2's slab
    assert rig.cad.drain(timeout_s=5.0) >= 1  # that release reached the cadence (ipc is asynchronous)
    rig.cad.frame_ema_ms = 800.0
    assert rig.cad.stall_s == pytest.approx(8.0)
    rig.push(10, 5)
    assert rig.tick(advance=5.5) is False
    assert rig.tick(advance=2.6)    # 8.1 s after the last progress (the publish of h3) > 8 s


def test_late_ticks_skipped_and_counted(rig):
    rig.tick()
    h = rig.tick(advance=0.035)  # 3.5 periods of 10 ms: 2 deadlines unservable
    assert rig.cad.stats()["skipped"]["late"] == 2
    assert rig.cad.ticks == 2


def test_hello_resets_reader_and_next_handoff_is_full(tmp_path):
    rig = Rig(tmp_path, latest_only=False)
    try:
        _hello(rig)
    finally:
        rig.close()


def _hello(rig):
    rig.push(10, 1)
    rig.tick(); rig.recv()
    rig.push(10, 2)
    h = rig.tick()
    assert h.dirty is not None   # incremental
    assert rig.tick() is False   # both held
    rig.send(encode_hello(os.getpid(), 1))
    h = rig.tick()
    assert h and h.dirty is None  # full copy for the new renderer
    assert rig.cad.stats()["renderer_hellos"] == 1


def test_idle_renderer_frees_slabs_whose_release_was_lost(tmp_path):
    """A renderer that holds nothing and got no handoff for a while says so (``idle`` with
    the newest seq it received): the cadence frees the slabs it has seen, keeps the one in
    flight, and a restarted cadence frees what its predecessor handed out (the releases
    queued to a frozen cadence die with it; the soak's renderer starved for 75 s)."""
    rig = Rig(tmp_path, latest_only=False)
    try:
        rig.push(10, 1)
        h1 = rig.tick()
        got, _ = rig.recv()                  # the renderer draws A ...
        rig.reader._held = None              # ... and its release is lost
        h2 = rig.tick()                      # B goes out while the renderer is busy: in flight
        assert rig.tick() is False and rig.cad.stats()["skipped"] == {"renderer_busy": 1}
        rig.send(encode_idle(h1.seq, 600.0))
        assert rig.cad.writer.held == (h2.slab == 0, h2.slab == 1)  # A freed, B still out
        assert rig.cad.stats()["renderer_resyncs"] == 1
        h3 = rig.tick()
        assert h3 and h3.slab == h1.slab
        # the cadence dies with both slabs out (their releases lost); a new one starts from
        # the slab headers and would wait for the renderer forever
        rig.cad.close()
        rig.cad = Cadence(rig.ring, rig.slabs, rig.ready, rig.rel, rig.z, rig.cfg, rig.decision,
                          clock=rig.clk, sleep=rig.clk.sleep, latest_only=False)
        assert rig.cad.writer.held == (True, True)
        assert rig.tick() is False and rig.cad.stats()["skipped"] == {"renderer_busy": 1}
        rig.send(encode_idle(h1.seq, 600.0))  # it never saw h2, h3 (lost with the old cadence)
        assert rig.cad.writer.held == (False, False)
        h4 = rig.tick()
        assert h4 and h4.seq == h3.seq + 1 and h4.dirty is None  # full: nothing is known of the renderer
        # idle with nothing to free changes nothing and is not counted
        rig.send(encode_idle(h3.seq, 600.0))
        assert rig.cad.writer.held[h4.slab] and rig.cad.stats()["renderer_resyncs"] == 1
    finally:
        rig.close()


def test_adaptive_interval_follows_frame_time_ema(tmp_path):
    r = Rig(tmp_path, {"cadence": {"adaptive": True}, "policy": {"tier": "H", "mode": "max_throughput"}})
    try:
        assert r.cad.interval_ms == pytest.approx(78.125)
        r.send(encode_frame_time(60.0, 1))
        assert r.cad.frame_ema_ms == pytest.approx(60.0)
        assert r.cad.interval_ms == pytest.approx(120.0)
        r.send(encode_frame_time(100.0, 2))
        assert r.cad.frame_ema_ms == pytest.approx(60.0 + 0.15 * 40.0)
        assert r.cad.interval_ms == pytest.approx(132.0)
        assert r.cad.ticker.interval_s == pytest.approx(0.132)
        r.send(encode_frame_time(1000.0, 3))
        assert r.cad.interval_ms == pytest.approx(200.0)
    finally:
        r.close()


def test_fixed_mode_ignores_frame_time(rig):
    rig.send(encode_frame_time(500.0, 1))
    assert rig.cad.frame_ema_ms == 500.0
    assert rig.cad.interval_ms == pytest.approx(10.0)


def test_bad_control_message_counted_not_fatal(rig):
    rig.send([CONTROL_TAG, b"garbage"])
    rig.send([b"junk"])          # unknown tag: handed to the writer, which ignores it
    assert rig.cad.stats()["bad_messages"] == 1
    rig.push(5, 3)
    assert rig.tick()


def test_no_renderer_counted(tmp_path):
    r = Rig(tmp_path, bind_renderer=False)
    try:
        assert r.tick() is False
        assert r.cad.stats()["skipped"] == {"no_reader": 1}
    finally:
        r.close()


def test_hello_gpu_info_refines_policy(rig):
    assert rig.cad.decision.point_budget == 5000          # tier M from config, ring cap
    gpu = {"name": "tiny", "type": "DiscreteGPU", "max_storage_binding": 16 * 1000, "max_buffer_size": 1 << 30}
    rig.send(encode_hello(os.getpid(), 0, gpu=gpu))
    d = rig.cad.decision
    assert d.point_budget == 1000 and d.hardware.gpu_name == "tiny"
    assert [c.name for c in d.caps if c.applied][-1] == "gpu_storage"
    rig.push(5, 1)
    assert rig.tick().extra["budget"] == 1000             # the renderer gets the new budget
    assert rig.cad.stats()["budget"] == 1000


def test_hello_gpu_info_detects_tier(tmp_path):
    r = Rig(tmp_path, {"policy": {"tier": "auto"}})
    try:
        cpu_only = r.cad.decision.tier
        r.send(encode_hello(os.getpid(), 0, gpu={"name": "lavapipe", "type": "CPU", "max_storage_binding": 1 << 27}))
        assert r.cad.decision.tier == "L" and r.cad.decision.tier_source == "detected"
        assert any(x.startswith("gpu: lavapipe") for x in r.cad.decision.tier_reasons)
        assert cpu_only in ("L", "M", "H")
    finally:
        r.close()


def test_latest_only_waits_out_a_slow_frame(rig):
    """On a loaded machine one frame in a few took 2-3x the frame-time EMA; the cadence used
    to hand out its second slab mid-frame (after 3 EMAs without progress), and that snapshot
    then waited in the queue until the frame ended. It now waits 10 of the slowest recent
    frames (at least STALL_S): a renderer whose messages were lost says so itself (idle)."""
    from pointflow.cadence.process import STALL_S

    assert rig.cad.stall_s == STALL_S
    for ms in (400.0, 400.0, 400.0, 1100.0, 400.0):
        rig.cad.on_frame_time(ms)
    assert rig.cad.frame_ema_ms < 600.0
    assert rig.cad.stall_s == pytest.approx(10 * 1.1)
    rig.push(10, 1)
    h1 = rig.tick()
    rig.recv()                                  # the renderer starts a (slow) frame
    rig.push(10, 2)
    assert rig.tick(advance=3.0) is False       # 3 s: 3 EMAs (the old rule) passed; still waiting
    assert rig.tick(advance=7.5) is False       # 10.5 s < 11 s
    assert rig.tick(advance=0.6)                # 11.1 s: the renderer is taken to be stuck
    assert rig.cad.stats()["skipped"]["renderer_pending"] == 2
    assert h1.seq < rig.cad.last_pub_seq


def test_a_renderer_that_reports_frames_is_done_when_it_says_so(rig):
    """The renderer gives its slab back as soon as its frame no longer reads it; on lavapipe
    the GPU work then goes on for ~1 s, and a snapshot taken at the release waited that long
    before it was drawn. Once a renderer reports its frames, only the report (or an
    ``idle``) lets the next snapshot go; ``drawn: false`` (nothing to frame) does at once
    and leaves the frame-time EMA alone."""
    rig.push(10, 1)
    h1 = rig.tick()
    rig.recv()
    rig.release()                               # no frame reports yet: the release is progress
    rig.send(encode_frame_time(40.0, h1.seq))
    h2 = rig.tick()
    assert h2
    rig.recv()
    rig.reader.release()                        # the frame's data is uploaded; GPU still busy
    time.sleep(0.05)
    rig.cad.drain(0.2)
    rig.push(10, 2)
    assert rig.tick() is False                  # not done yet: no snapshot that would wait
    assert rig.cad.stats()["skipped"]["renderer_pending"] >= 1
    rig.send(encode_frame_time(900.0, h2.seq))  # the frame is complete
    h3 = rig.tick()
    assert h3 and h3.trace_ids == [2]
    rig.recv()
    ema = rig.cad.frame_ema_ms
    rig.send(encode_frame_time(0.0, h3.seq, drawn=False))
    assert rig.cad.frame_ema_ms == ema
    assert rig.tick()


def test_a_first_cadence_waits_for_the_renderer_to_speak(tmp_path):
    """At a pipeline's start the renderer binds its socket seconds before it can draw
    (device, warm-up frame); a snapshot sent then was stale when drawn, and the stall rule
    added a second. The first cadence publishes once the renderer has said anything."""
    rig = Rig(tmp_path)
    try:
        rig.cad.renderer_heard = False
        rig.push(10, 1)
        assert rig.tick() is False and rig.tick() is False
        assert rig.cad.stats()["skipped"] == {"no_reader": 2}
        rig.send(encode_hello(os.getpid(), 0))
        h = rig.tick()
        assert h and h.dirty is None and h.trace_ids == [1]
    finally:
        rig.close()


def _slab_equals_ring(rig, slab):
    ring, dst = rig.ring.arrays, rig.slabs.arrays(slab)
    return all(np.array_equal(dst[k], a, equal_nan=True) for k, a in ring.items())  # unwritten channel slots are NaN


def test_ticks_while_the_renderer_draws_prefill_the_next_slab(rig):
    """The snapshot at a frame's end used to copy two frames' worth of changes (the whole
    ring at 1M points/s) while the next frame waited. The skipped ticks now copy them into
    the next slab ahead of time: the handoff then copies only what came since, and still
    carries every chunk committed since the previous handoff, once, with its ranges."""
    from pointflow.cadence.process import PREFILL_S

    rig.push(100, 1)
    h1 = rig.tick()
    got, _ = rig.recv()                         # the renderer draws slab h1.slab
    nxt = 1 - h1.slab
    rig.push(200, 2)
    assert rig.tick(advance=PREFILL_S + 0.001) is False  # renderer_pending: prefills the other slab
    st = rig.cad.writer.stats
    assert st["prefills"] == 1 and st["prefilled_slots"] >= 200
    assert _slab_equals_ring(rig, nxt)          # chunk 2 is in the next slab before any handoff
    rig.push(50, 3)
    assert rig.tick() is False                  # within PREFILL_S of the last copy: nothing copied
    assert st["prefills"] == 1
    rig.release()
    rig.send(encode_frame_time(500.0, h1.seq))
    copied = st["copied_slots"]
    h2 = rig.tick()
    assert h2 and h2.slab == nxt
    assert st["copied_slots"] - copied == 50    # only chunk 3 was left to copy
    assert h2.trace_ids == [2, 3]               # the prefilled chunk still rides on this handoff
    assert h2.dirty == [(100, 350)]             # and so do its ranges
    got, view = rig.recv()
    assert got.seq == h2.seq and view.size == 350
    assert _slab_equals_ring(rig, nxt)
    assert sorted(np.unique(view.channels["intensity"][:350]).tolist()) == [1.0, 2.0, 3.0]
    rig.spans.flush()
    time.sleep(0.05)
    rig.coll.poll(0)
    t = rig.coll.table()
    snap = t.event == t.event_names.index("cadence_snapshot")
    assert sorted(t.trace_id[snap].tolist()) == [1, 2, 3]  # each chunk once, at its handoff


def test_every_handoff_shows_the_ring_as_it_was_at_its_snapshot(tmp_path):
    """Prefills, handoffs, releases and frame reports in a random order, with the ring
    wrapping around many times: every handed-out slab equals the ring at its snapshot, and
    every committed chunk appears in exactly one handoff, in commit order."""
    from pointflow.cadence.process import PREFILL_S

    rig = Rig(tmp_path)
    try:
        rng = np.random.default_rng(7)
        tid, seen, last = 0, [], None
        for step in range(120):
            for _ in range(int(rng.integers(0, 3))):
                tid += 1
                rig.push(int(rng.integers(1, 900)), tid)
            h = rig.tick(advance=PREFILL_S + 0.001 if rng.random() < 0.7 else None)
            if h:
                assert _slab_equals_ring(rig, h.slab), f"step {step}: slab {h.slab} differs from the ring"
                seen += h.trace_ids
                got, _ = rig.recv()
                assert got.seq == h.seq
                last = h
            elif last is not None and rng.random() < 0.5:   # the frame ends
                rig.reader.release()
                rig.send(encode_frame_time(10.0, last.seq))  # after the release, on the same socket
        assert rig.cad.writer.stats["prefills"] > 10
        assert seen == sorted(seen) and len(seen) == len(set(seen))
        assert set(range(1, tid + 1)) - set(seen) <= set(range(seen[-1] + 1 if seen else 1, tid + 1))
    finally:
        rig.close()


def test_handoffs_that_never_reached_the_renderer_are_freed_after_its_idle(tmp_path):
    """Handoffs sent into the connection of a renderer that died (or before a hello that never
    came) are held forever by nobody: the 60-min chaos soak once drew no frame for 61 s after
    a frozen renderer was replaced. The new renderer says idle with the newest handoff it got;
    a later one sent long enough ago (the stall window) was lost: freed, next handoff full."""
    rig = Rig(tmp_path, latest_only=False)
    try:
        rig.push(10, 1)
        h1 = rig.tick()
        rig.recv()
        rig.release()
        rig.push(10, 2)
        h2 = rig.tick()
        rig.push(10, 3)
        h3 = rig.tick()
        for _ in (h2, h3):  # both lost on the way: the renderer never reads them
            assert rig.rpull.poll(1000)
            rig.rpull.recv_multipart()
        assert rig.cad.writer.held == (True, True) and rig.tick() is False
        rig.send(encode_idle(h1.seq, 600.0))  # too soon to call them lost: they may be in flight
        assert rig.cad.writer.held == (True, True) and rig.cad.stats()["lost_handoffs"] == 0
        rig.clk.advance(rig.cad.stall_s + 1.0)
        rig.send(encode_idle(h1.seq, 6000.0))
        assert rig.cad.writer.held == (False, False) and rig.cad.stats()["lost_handoffs"] == 2
        h4 = rig.tick()
        assert h4 and h4.dirty is None  # full: the renderer missed h2's and h3's changes
        got, view = rig.recv()
        assert got.seq == h4.seq and int(view.positions.shape[0]) >= 30
    finally:
        rig.close()


def test_a_handoff_for_a_slab_written_again_since_is_not_read(rig):
    """The renderer's side of the same rule: a handoff that arrives after its slab was freed
    as lost and written again (its seq in the slab header is newer) is skipped, not drawn."""
    from pointflow.ring.slabs import S_SEQ

    rig.push(10, 1)
    h = rig.tick()
    rig.slabs.state(h.slab)[S_SEQ] = h.seq + 2  # the cadence reused the slab meanwhile
    assert rig.reader.recv(1000) is None and rig.reader.held is None
