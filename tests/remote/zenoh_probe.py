"""A receiving end in one process: the real ``zenoh`` transport, run until the senders said
they stopped; writes every received position (in order) and the transport's counters.

Usage: python zenoh_probe.py OPTIONS_JSON OUT_PREFIX SENDERS TIMEOUT_S [HOLD_S]

HOLD_S: wait this long after subscribing before taking any sample (a slow viewer: the
transport's bounded queue overflows meanwhile).
"""
from __future__ import annotations

import json
import sys
import time

import numpy as np

from pointflow.ingest.transports.zenoh_transport import ZenohTransport


def main() -> int:
    opts, out, senders, timeout = json.loads(sys.argv[1]), sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
    hold = float(sys.argv[5]) if len(sys.argv) > 5 else 0.0
    t = ZenohTransport(ZenohTransport.validate_options(opts, "probe", "."), "probe")
    t.open()
    print("probe: listening", flush=True)
    time.sleep(hold)
    pos, end = [], time.monotonic() + timeout
    try:
        for chunk in t.chunks():
            if chunk is not None:
                pos.append(np.asarray(chunk.positions, np.float64))
            if len(t.ledger.ended) >= senders or time.monotonic() > end:
                break
    finally:
        t.close()
    np.save(out + ".npy", np.concatenate(pos) if pos else np.zeros((0, 3)))
    with open(out + ".json", "w") as f:
        json.dump({**t.counters, "ended": sorted(t.ledger.ended)}, f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
