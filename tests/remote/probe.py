"""A receiving host in one process: the real ``zmq`` transport, run until the senders said
they stopped; writes every received position (in order) and the transport's counters.

Usage: python probe.py OPTIONS_JSON OUT_PREFIX SENDERS TIMEOUT_S
"""
from __future__ import annotations

import json
import sys
import time

import numpy as np

from pointflow.ingest.transports.zmq_transport import ZmqTransport


def main() -> int:
    opts, out, senders, timeout = json.loads(sys.argv[1]), sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
    t = ZmqTransport(ZmqTransport.validate_options(opts, "probe", "."), "probe")
    t.open()
    print("probe: listening", flush=True)
    return drain(t, out, senders, timeout, after=lambda: t._poll_monitor())


def drain(t, out: str, senders: int, timeout: float, after=None) -> int:
    """Take chunks from an open transport until ``senders`` said they stopped (or the
    timeout); write the positions to OUT.npy and the counters to OUT.json. Both probes
    (ZeroMQ and Zenoh) end this way."""
    pos, end = [], time.monotonic() + timeout
    try:
        for chunk in t.chunks():
            if chunk is not None:
                pos.append(np.asarray(chunk.positions, np.float64))
            if len(t.ledger.ended) >= senders or time.monotonic() > end:
                break
        if after is not None:
            after()
    finally:
        t.close()
    np.save(out + ".npy", np.concatenate(pos) if pos else np.zeros((0, 3)))
    with open(out + ".json", "w") as f:
        json.dump({**t.counters, "ended": sorted(t.ledger.ended)}, f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
