import multiprocessing as mp
import os
import time
import zlib

import numpy as np
import pytest
import zmq

from pointflow.ring import Handoff, PointRing, RingAttachError, SlabPair, SlabReader, SlabWriter

from .helpers import xrange_pts


def test_handoff_encode_decode_roundtrip():
    h = Handoff(seq=7, slab=1, count=10, head=3, capacity=16, origin=(1.5, 2.0, -3.0), dirty=[(0, 4), (9, 16)],
                epoch_ns=123, t_snapshot_ns=456, channel_ranges={"importance": (0.1, 0.9)},
                trace_ids=[1, (1 << 63) + 2], extra={"budget": 5}, t_commit_ns=[11, 12])
    assert Handoff.decode(h.encode()) == h
    h.dirty = None
    assert Handoff.decode(h.encode()).dirty is None
    with pytest.raises(ValueError):
        Handoff.decode([b"nope", b"{}", b"", b""])


def _sockets(ctx, tag):
    ready_pull = ctx.socket(zmq.PULL)
    ready_pull.bind(f"inproc://ready-{tag}")
    rel_pull = ctx.socket(zmq.PULL)
    rel_pull.bind(f"inproc://rel-{tag}")
    ready_push = ctx.socket(zmq.PUSH)
    ready_push.connect(f"inproc://ready-{tag}")
    rel_push = ctx.socket(zmq.PUSH)
    rel_push.connect(f"inproc://rel-{tag}")
    return ready_push, rel_pull, ready_pull, rel_push


class Mirror:
    """What a renderer keeps on the GPU: updated only through dirty ranges."""

    def __init__(self, cap):
        self.pos = np.zeros((cap, 3), np.float32)

    def apply(self, h, view):
        for a, b in ([(0, view.capacity)] if h.dirty is None else h.dirty):
            self.pos[a:b] = view.positions[a:b]
        occ = view.valid
        assert np.array_equal(self.pos[occ], view.positions[occ])


def test_writer_reader_in_process():
    ctx = zmq.Context()
    with PointRing(100, channels=["intensity"]) as ring, SlabPair.create(ring.layout) as slabs:
        w_ready, w_rel, r_ready, r_rel = _sockets(ctx, "t1")
        writer = SlabWriter(ring, slabs, w_ready, w_rel)
        reader = SlabReader(SlabPair.attach(slabs.names), r_ready, r_rel)
        mirror = Mirror(100)
        ring.push(xrange_pts(0, 10), intensity=np.arange(10.0), trace_id=42)
        h1 = writer.publish({"budget": 1})
        assert h1.dirty is None and h1.count == 10 and h1.trace_ids == [42] and h1.extra == {"budget": 1}
        assert h1.channel_ranges["intensity"] == (0.0, 9.0) and h1.channel_ranges["importance"] == (1.0, 1.0)
        h, view = reader.recv(1000)
        assert h == h1 and view.size == 10 and np.array_equal(view.world_positions()[:, 0], np.arange(10.0))
        mirror.apply(h, view)
        ring.push(xrange_pts(10, 15))
        h2 = writer.publish()
        assert h2.slab != h1.slab and h2.dirty == [(10, 15)] and h2.trace_ids == []
        # the reader holds one slab, the writer's other is in flight: both busy
        assert writer.publish() is None
        h, view = reader.recv(1000)  # takes h2, releases h1's slab
        mirror.apply(h, view)
        assert view.channel_present("intensity").sum() == 10
        h3 = writer.publish()  # nothing changed: still published, dirty == []
        assert h3 is not None and h3.dirty == [] and h3.slab == h1.slab
        h, view = reader.recv(1000)
        mirror.apply(h, view)
        # ring wraps twice while the reader is slow: publishes are refused while it holds both slabs,
        # and the changes they missed are carried to the next handoff
        published = []
        for i in range(20):
            ring.push(xrange_pts(100 + 13 * i, 113 + 13 * i))
            published.append(writer.publish())
        assert published[0] is not None and published[1:] == [None] * 19
        h, view = reader.recv(1000)
        mirror.apply(h, view)
        reader.release(h.slab)
        assert writer.publish() is not None
        h, view = reader.recv(1000)
        mirror.apply(h, view)
        assert np.array_equal(view.world_positions()[:, 0], np.arange(100 + 13 * 20 - 100, 100 + 13 * 20))
        # reset: next handoff is full, origin re-chosen
        ring.reset()
        ring.push(xrange_pts(1000, 1003))
        reader.release(h.slab)
        h = writer.publish()
        assert h.dirty is None and h.count == 3 and h.origin == (1001.0, 0.0, 0.0)  # the median of that push
        # renderer restart: a new reader holds nothing; the cadence resets its view of the renderer
        reader2 = SlabReader(reader.slabs, r_ready, r_rel)
        while reader2.recv(50):
            pass
        writer.reset_reader()
        h = writer.publish()
        assert h.dirty is None
        got, view = reader2.recv(1000)
        assert got.seq == h.seq
        reader.slabs.close()
        for s in (w_ready, w_rel, r_ready, r_rel):
            s.close(0)
    ctx.term()


def test_writer_state_survives_cadence_restart():
    ctx = zmq.Context()
    with PointRing(10) as ring, SlabPair.create(ring.layout) as slabs:
        w_ready, w_rel, r_ready, r_rel = _sockets(ctx, "t2")
        w1 = SlabWriter(ring, slabs, w_ready, w_rel)
        reader = SlabReader(slabs, r_ready, r_rel)
        ring.push(xrange_pts(0, 3))
        h1 = w1.publish()
        reader.recv(1000)
        w2 = SlabWriter(ring, slabs, w_ready, w_rel)  # a restarted cadence
        assert w2.held == tuple(i == h1.slab for i in (0, 1))
        h2 = w2.publish()
        assert h2.slab != h1.slab and h2.seq > h1.seq and h2.dirty is None
        assert w2.publish() is None  # never writes the slab the reader holds
        for s in (w_ready, w_rel, r_ready, r_rel):
            s.close(0)
    ctx.term()


def test_slab_attach_validation():
    with PointRing(10) as ring, SlabPair.create(ring.layout) as slabs:
        with pytest.raises(RingAttachError):
            SlabPair.attach((ring.name, ring.name))
        with pytest.raises(RingAttachError):
            SlabPair.attach(slabs.names, layout=PointRing(5).layout if False else None) if False else SlabPair.attach(
                (slabs.names[0], "pfslab_missing"))
        a = SlabPair.attach(slabs.names)
        a.close()
        assert all(os.path.exists("/dev/shm/" + n) for n in slabs.names)


# ---------------------------------------------------------------- multi-process stress
def _crc(view):
    return zlib.crc32(view.positions.data, zlib.crc32(view.generation.data, zlib.crc32(view.t_ingest_ms.data)))


def _ingest_proc(ring_name, stop_at):
    ring = PointRing.attach(ring_name)
    x = 0
    rng = np.random.default_rng(os.getpid())
    while x < stop_at:
        n = int(rng.integers(1, 300))
        ring.push(xrange_pts(x, x + n), trace_id=x + 1)
        x += n
        if rng.random() < 0.3:
            time.sleep(0.0002)
    ring.close()


def _cadence_proc(ring_name, slab_names, ready_addr, rel_addr, n_handoffs, out_q):
    ctx = zmq.Context()
    ready = ctx.socket(zmq.PUSH)
    ready.connect(ready_addr)
    rel = ctx.socket(zmq.PULL)
    rel.bind(rel_addr)
    ring = PointRing.attach(ring_name)
    slabs = SlabPair.attach(slab_names)
    writer = SlabWriter(ring, slabs, ready, rel)
    crcs = {}
    published = 0
    busy = 0
    while published < n_handoffs:
        h = writer.publish()
        if h is None:
            busy += 1
            time.sleep(0.0001)
            continue
        crcs[h.seq] = _crc(slabs.slab_view(h.slab))  # read-only while the renderer may read too
        published += 1
    writer.publish({"done": True}) or None
    while True:  # make sure the final marker goes out
        h = writer.publish({"done": True})
        if h is not None:
            break
        time.sleep(0.001)
    out_q.put(("cadence", crcs, busy))
    time.sleep(0.5)
    ready.close(1000)
    rel.close(0)
    ctx.term()
    ring.close()
    slabs.close()


def _render_proc(slab_names, ready_addr, rel_addr, out_q):
    ctx = zmq.Context()
    ready = ctx.socket(zmq.PULL)
    ready.bind(ready_addr)
    rel = ctx.socket(zmq.PUSH)
    rel.connect(rel_addr)
    slabs = SlabPair.attach(slab_names)
    reader = SlabReader(slabs, ready, rel)
    rng = np.random.default_rng(1)
    results = {}
    errors = []
    mirror = None
    while True:
        got = reader.recv(5000)
        if got is None:
            errors.append("timeout")
            break
        h, view = got
        if mirror is None:
            mirror = np.zeros((view.capacity, 3), np.float32)
            if h.dirty is not None:
                errors.append("first handoff not full")
        c1 = _crc(view)
        xs = view.world_positions()[:, 0]
        if view.size != h.count or not np.array_equal(np.diff(xs), np.ones(len(xs) - 1)):
            errors.append(f"torn snapshot seq={h.seq}")
        for a, b in ([(0, view.capacity)] if h.dirty is None else h.dirty):
            mirror[a:b] = view.positions[a:b]
        occ = view.valid
        if not np.array_equal(mirror[occ], view.positions[occ]):
            errors.append(f"dirty ranges missed a change at seq={h.seq}")
        if rng.random() < 0.5:
            time.sleep(float(rng.random()) * 0.0005)
        c2 = _crc(view)
        results[h.seq] = (c1, c2)
        if h.extra.get("done"):
            break
        if rng.random() < 0.5:
            reader.release(h.slab)  # otherwise held until the next recv
    reader.release()
    out_q.put(("render", results, errors))
    time.sleep(0.3)
    rel.close(1000)
    ready.close(0)
    ctx.term()
    slabs.close()


def test_concurrent_handoff_stress(tmp_path):
    n_handoffs = int(os.environ.get("PF_RING_STRESS_HANDOFFS", "3000"))
    spawn = mp.get_context("spawn")
    ready_addr = f"ipc://{tmp_path}/ready"
    rel_addr = f"ipc://{tmp_path}/rel"
    q = spawn.Queue()
    with PointRing(4096) as ring, SlabPair.create(ring.layout) as slabs:
        ring.push(xrange_pts(-1, 0))
        render = spawn.Process(target=_render_proc, args=(slabs.names, ready_addr, rel_addr, q))
        render.start()
        ingest = spawn.Process(target=_ingest_proc, args=(ring.name, 10**12))
        cadence = spawn.Process(target=_cadence_proc,
                                args=(ring.name, slabs.names, ready_addr, rel_addr, n_handoffs, q))
        ingest.start()
        cadence.start()
        out = {}
        try:
            for _ in range(2):
                kind, *rest = q.get(timeout=240)
                out[kind] = rest
        finally:
            ingest.terminate()  # ingest runs until stopped
            for p in (ingest, cadence, render):
                p.join(30)
                if p.is_alive():
                    p.kill()
        crcs, busy = out["cadence"]
        results, errors = out["render"]
        assert errors == []
        assert len(crcs) >= n_handoffs
        checked = 0
        for seq, (c1, c2) in results.items():
            assert c1 == c2, f"slab changed while the renderer held it (seq {seq})"
            if seq in crcs:
                assert crcs[seq] == c1, f"renderer saw different bytes than the cadence wrote (seq {seq})"
                checked += 1
        assert checked >= n_handoffs // 3
        assert ring.stats().write_count > 10


def test_coalesced_push_reports_every_trace_id():
    """One push carrying several coalesced chunks puts each chunk's trace id in the commit
    log, so the cadence's handoff names all of them (profiling sees every chunk)."""
    import zmq

    from pointflow.ring import PointRing, SlabPair
    from pointflow.ring.handoff import SlabReader, SlabWriter

    ctx = zmq.Context()
    ring = PointRing(100, channels=["intensity"])
    slabs = SlabPair.create(ring.layout)
    try:
        ready_w, ready_r = ctx.socket(zmq.PUSH), ctx.socket(zmq.PULL)
        rel_w, rel_r = ctx.socket(zmq.PUSH), ctx.socket(zmq.PULL)
        ready_r.bind("inproc://tid-ready"); ready_w.connect("inproc://tid-ready")
        rel_r.bind("inproc://tid-rel"); rel_w.connect("inproc://tid-rel")
        writer = SlabWriter(ring, slabs, ready_w, rel_r)
        reader = SlabReader(slabs, ready_r, rel_w)
        ring.push(np.zeros((6, 3)), trace_id=[11, 0, 12, 13], intensity=np.ones(6, np.float32))
        ring.push(np.ones((2, 3)), trace_id=14, intensity=np.ones(2, np.float32))
        assert writer.publish() is not None
        h, _view = reader.recv(timeout_ms=1000)
        assert sorted(h.trace_ids) == [11, 12, 13, 14]
        reader.release()
        for s in (ready_w, ready_r, rel_w, rel_r):
            s.close(0)
    finally:
        slabs.close(); slabs.unlink(); ring.close(); ring.unlink()
        ctx.term()
