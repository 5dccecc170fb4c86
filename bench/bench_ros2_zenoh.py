"""ROS 2 over rmw_zenoh: Ouster-size PointCloud2 through a Zenoh router into the ``ros2_zenoh``
transport, against the engine alone in the same run.

A router process and a publisher process behaving as rmw_zenoh's (``pointflow/testing/rmw_zenoh_pub.py``)
send ``--messages`` clouds of 131,072 points (48-byte points, 6.3 MB of CDR each) as fast as
Zenoh takes them. Two receivers, interleaved over ``--repeats``:

* ``engine``: a bare Zenoh subscriber on the same key that only copies each payload out
  (``payload.to_bytes()``): what the engine delivers on this machine;
* ``transport``: the ``ros2_zenoh`` transport (discovery, tokens, attachment and sequence
  ledger, rosbags deserialisation, the PointCloud2 decoder, positions + intensity), iterated
  as the source loop does.

Rate = (messages received - 1) / (time from the first arrival to the last one handled). The
ratio transport / engine is the figure; messages lost on the way (best effort drops whole
fragmented samples under pressure) are reported, for the transport from its own ledger.

    .venv/bin/python bench/bench_ros2_zenoh.py [--repeats 3] [--messages 30] [--reliable] [--out FILE]

Writes ``bench/results/ros2_zenoh.json`` (or ``--out``).
"""
from __future__ import annotations

import argparse
import json
import os
import pickle
import statistics
import tempfile
import threading
import time

import numpy as np

import _harness as H
from pointflow.ingest import rmw_zenoh as rz
from pointflow.testing import rmw_zenoh_pub as P
from pointflow.ingest.transports import resolve_transport
from pointflow.testing import LineProc, free_port

TOPIC = "/ouster/points"
N_POINTS = 131_072


def ouster_payload(seed: int = 0) -> bytes:
    """x y z float32, 4 pad, intensity float32, t uint32, reflectivity/ring/ambient uint16, range
    uint32, 12 pad: 48 bytes a point, as ouster-ros sends (packed with numpy, CDR by rosbags)."""
    from rosbags.typesys import Stores, get_typestore

    rng = np.random.default_rng(seed)
    dt = np.dtype({"names": ["x", "y", "z", "intensity", "t", "reflectivity", "ring", "ambient", "range"],
                   "formats": ["<f4", "<f4", "<f4", "<f4", "<u4", "<u2", "<u2", "<u2", "<u4"],
                   "offsets": [0, 4, 8, 16, 20, 24, 26, 28, 32], "itemsize": 48})
    rec = np.zeros(N_POINTS, dt)
    for k in ("x", "y", "z", "intensity"):
        rec[k] = rng.uniform(-50, 50, N_POINTS)
    ts = get_typestore(Stores.LATEST)
    T = ts.types
    codes = {"<f4": 7, "<u4": 6, "<u2": 4}
    fields = [T["sensor_msgs/msg/PointField"](name=n, offset=dt.fields[n][1], datatype=codes[dt.fields[n][0].str], count=1)
              for n in dt.names]
    msg = T["sensor_msgs/msg/PointCloud2"](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1_700_000_000, nanosec=0), frame_id="os"),
        height=1, width=N_POINTS, fields=fields, is_bigendian=False, point_step=48, row_step=48 * N_POINTS,
        data=np.frombuffer(rec.tobytes(), np.uint8), is_dense=True)
    return bytes(ts.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))


def run_once(kind: str, loc: str, spec_path: str, n: int) -> dict:
    import zenoh

    pub = LineProc(["-m", P.__name__, spec_path])
    pub.wait_line("READY")
    arrivals: list[float] = []
    done_t: list[float] = []
    out: dict = {"kind": kind}
    if kind == "engine":
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("connect/endpoints", json.dumps([loc]))
        conf.insert_json5("listen/endpoints", "[]")
        conf.insert_json5("scouting/multicast/enabled", "false")
        s = zenoh.open(conf)
        seen: list[int] = []
        lock = threading.Lock()

        def cb(sample):
            data = sample.payload.to_bytes()
            att = rz.parse_attachment(sample.attachment)
            with lock:
                arrivals.append(time.perf_counter())
                seen.append(att.sequence_number)
                done_t.append(time.perf_counter())
                assert len(data) > 1000
        sub = s.declare_subscriber(rz.topic_key(0, TOPIC, P.PC2), cb)
        time.sleep(1.0)  # the declaration reaches the publisher
        pub.send("go\n")
        pub.wait_line("SENT", 120)
        end = time.monotonic() + 10
        while len(seen) < n and time.monotonic() < end:
            time.sleep(0.05)
        sub.undeclare()
        s.close()
        out["received"] = len(seen)
        out["lost"] = (max(seen) - min(seen) + 1 - len(seen)) if seen else n
    else:
        cls = resolve_transport("ros2_zenoh")
        t = cls(cls.validate_options({"topic": TOPIC, "zenoh": {"connect": [loc]}, "queue_messages": 4,
                                      "channels": ["intensity"]}, "options"), "bench")
        t.open()
        pub.wait_line("MATCHED")
        time.sleep(1.0)
        pub.send("go\n")
        it = t.chunks()
        got = 0
        end = time.monotonic() + 120
        while got + t.counters.get("lost_in_transit_messages", 0) + t.counters["dropped_queue_full"] < n \
                and time.monotonic() < end:
            c = next(it)
            if c is not None:
                got += 1
                if got == 1:
                    arrivals.append(time.perf_counter())
                done_t.append(time.perf_counter())
        out.update(received=got, lost=t.counters.get("lost_in_transit_messages", 0),
                   dropped_queue_full=t.counters["dropped_queue_full"],
                   deserialize_s=t.counters["deserialize_s"], decode_s=t.counters["decode_s"])
        t.close()
    pub.close()
    if out["received"] > 1:
        el = done_t[-1] - arrivals[0]
        out["msgs_per_s"] = (out["received"] - 1) / el
        out["mpoints_per_s"] = out["msgs_per_s"] * N_POINTS / 1e6
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--messages", type=int, default=30)
    ap.add_argument("--reliable", action="store_true", help="a reliable publisher (default: best effort, as sensor QoS)")
    ap.add_argument("--out", default=str(H.RESULTS / "ros2_zenoh.json"))
    a = ap.parse_args()
    machine = H.machine()
    payload = ouster_payload()
    loc = f"tcp/127.0.0.1:{free_port()}"
    router = LineProc(["-m", P.__name__, "--router", loc])
    router.wait_line("READY")
    tmp = tempfile.mkdtemp(prefix="bench-ros2-zenoh-")
    spec_path = os.path.join(tmp, "spec.pickle")
    with open(spec_path, "wb") as f:
        pickle.dump({"connect": loc, "mode": "jazzy", "advertise": [(TOPIC, P.PC2)], "period_s": 0.0,
                     "reliable": a.reliable, "script": [("put", TOPIC, payload)] * a.messages}, f)
    rows = []
    try:
        for r in range(a.repeats):
            for kind in H.order(("engine", "transport"), r):
                row = run_once(kind, loc, spec_path, a.messages)
                row["repeat"] = r
                rows.append(row)
                print(json.dumps({k: (round(v, 3) if isinstance(v, float) else v) for k, v in row.items()}), flush=True)
    finally:
        router.close()
        os.remove(spec_path)
        os.rmdir(tmp)
    med = {k: statistics.median([x["msgs_per_s"] for x in rows if x["kind"] == k and "msgs_per_s" in x])
           for k in ("engine", "transport")}
    res = {"machine": H.machine_done(machine), "command": H.command(),
           "payload_bytes": len(payload), "points": N_POINTS, "messages": a.messages, "reliable": a.reliable,
           "median_msgs_per_s": med, "ratio_transport_vs_engine": med["transport"] / med["engine"], "runs": rows}
    H.write_result(a.out, res, indent=1)
    print(f"engine {med['engine']:.1f} msg/s, transport {med['transport']:.1f} msg/s "
          f"({med['transport'] * N_POINTS / 1e6:.1f} Mpoints/s), ratio {res['ratio_transport_vs_engine']:.2f}")


if __name__ == "__main__":
    main()
