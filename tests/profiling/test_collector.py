"""SpanCollector: real SpanEmitter processes → PULL; bounded memory; bad batches counted."""
import json
import multiprocessing as mp
import time

import numpy as np
import pytest
import zmq

from pointflow.profiling.collector import SpanCollector
from pointflow.profiling.spans import SpanEmitter


def _emit(endpoint, stage, n, base_tid):
    z = zmq.Context()
    em = SpanEmitter(z, endpoint, stage, batch=64, flush_ms=10)
    for i in range(n):
        em.record(base_tid + i, "ingest_packed", 1000 + i, 2000 + i, 10)
    em.close()
    z.term()


def drain(coll, want, timeout=10.0):
    end = time.monotonic() + timeout
    while len(coll) < want and time.monotonic() < end:
        coll.poll(100)
    return len(coll)


def test_spans_from_two_processes(tmp_path):
    z = zmq.Context()
    ep = f"ipc://{tmp_path}/trace.sock"
    coll = SpanCollector(z, ep)
    ctx = mp.get_context("spawn")
    ps = [ctx.Process(target=_emit, args=(ep, f"stage{k}", 300, 1 + 10_000 * k)) for k in range(2)]
    for p in ps:
        p.start()
    assert drain(coll, 600) == 600
    for p in ps:
        p.join(10)
    t = coll.table()
    assert sorted(t.stage_names) == ["stage0", "stage1"]
    assert set(coll.processes) == {p.pid for p in ps}
    assert sorted(t.trace_id.tolist()) == list(range(1, 301)) + list(range(10_001, 10_301))
    k = t.trace_id.tolist().index(10_005)
    assert t.stage_names[t.stage[k]] == "stage1" and t.t1_ns[k] - t.t0_ns[k] == 1000 and t.n[k] == 10
    assert coll.counters()["received"] == 600 and coll.dropped == 0
    coll.close()
    z.term()


def test_bounded_keeps_newest_and_counts_dropped():
    coll = SpanCollector(None, None, max_spans=100)
    for b in range(7):
        spans = [[b * 30 + i + 1, "frame_done", i, i + 1, 0] for i in range(30)]
        coll.add_batch(json.dumps({"stage": "render", "pid": 1, "spans": spans}).encode())
    assert len(coll) == 100 and coll.dropped == 110 and coll.received == 210
    assert coll.table().trace_id.tolist() == list(range(111, 211))  # the newest, in order
    big = [[1000 + i, "frame_done", 0, 1, 0] for i in range(250)]   # one batch over the cap
    coll.add_batch(json.dumps({"stage": "render", "pid": 1, "spans": big}).encode())
    assert coll.table().trace_id.tolist() == list(range(1150, 1250))
    assert coll.dropped == 360


@pytest.mark.parametrize("msg", [b"not json", b'{"stage": "x"}', b'{"stage":"x","pid":1,"spans":5}',
                                 b'{"stage":"x","pid":1,"spans":[["a","ev",1,2,3]]}'])
def test_bad_batches_counted(msg):
    coll = SpanCollector(None, None)
    assert coll.add_batch(msg) == 0
    assert coll.bad_batches == 1 and len(coll) == 0
    # a batch with some malformed spans keeps the good ones
    ok = {"stage": "s", "pid": 2, "spans": [[5, "ev", 1, 2, 3], [1, 2], "x"]}
    assert coll.add_batch(json.dumps(ok).encode()) == 1
    assert coll.bad_spans == 2 and coll.table().event_names[coll.table().event[0]] == "ev"


def test_binary_batches_and_bad_binary_batches():
    z = zmq.Context()
    coll = SpanCollector(z, "inproc://t")
    em = SpanEmitter(z, "inproc://t", "render", batch=3)
    em.record(2**63 + 5, "frame_done", 10, 20, 7)      # full 64-bit trace id survives
    em.record(9, "custom_event", 30, 40, 0)             # events beyond EVENTS are named in the header
    em.record(0, "frame_done", 1, 2, 3)                 # trace id 0 = untraced: not recorded
    em.flush()
    assert coll.poll(1000) == 2
    t = coll.table()
    assert t.trace_id.tolist() == [2**63 + 5, 9]
    assert [t.event_names[e] for e in t.event] == ["frame_done", "custom_event"]
    assert t.t0_ns.tolist() == [10, 30] and t.t1_ns.tolist() == [20, 40] and t.n.tolist() == [7, 0]
    head = json.dumps({"v": 2, "stage": "x", "pid": 1, "events": ["a"]}).encode()
    assert coll.add_batch(head, b"\0" * 39) == 0                               # ragged body
    assert coll.add_batch(b"{", b"\0" * 40) == 0                               # bad header
    assert coll.add_batch(head, b"\0" * 40, b"extra") == 0                     # 3 frames
    body = np.array([[1, 0, 1, 2, 3], [2, 5, 1, 2, 3]], dtype="<u8").tobytes()  # event 5 unknown
    assert coll.add_batch(head, body) == 1
    assert coll.bad_batches == 3 and coll.bad_spans == 1
    em.close(); coll.close(); z.term()


def test_emitter_clamps_bad_values_without_misaligning():
    z = zmq.Context()
    coll = SpanCollector(z, "inproc://c")
    em = SpanEmitter(z, "inproc://c", "ingest", batch=100)
    em.record(1, "ingest_packed", 5, 6, 1)
    em.record(2, "ingest_packed", 7, -1, 2)   # negative end: clamped to 0, row stays aligned
    em.record(3, "ingest_packed", 8, 9, 3)
    em.close()
    assert coll.poll(1000) == 3
    t = coll.table()
    assert t.trace_id.tolist() == [1, 2, 3] and t.t1_ns.tolist() == [6, 0, 9] and t.n.tolist() == [1, 2, 3]
    coll.close(); z.term()
