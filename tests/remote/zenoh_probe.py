"""A receiving end in one process: the real ``zenoh`` transport, run until the senders said
they stopped; writes every received position (in order) and the transport's counters.

Usage: python zenoh_probe.py OPTIONS_JSON OUT_PREFIX SENDERS TIMEOUT_S [HOLD_S]

HOLD_S: wait this long after subscribing before taking any sample (a slow viewer: the
transport's bounded queue overflows meanwhile).
"""
from __future__ import annotations

import json
import os
import sys
import time

from pointflow.ingest.transports.zenoh_transport import ZenohTransport

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from probe import drain  # noqa: E402 - the ZeroMQ probe's ending, shared


def main() -> int:
    opts, out, senders, timeout = json.loads(sys.argv[1]), sys.argv[2], int(sys.argv[3]), float(sys.argv[4])
    hold = float(sys.argv[5]) if len(sys.argv) > 5 else 0.0
    t = ZenohTransport(ZenohTransport.validate_options(opts, "probe", "."), "probe")
    t.open()
    print("probe: listening", flush=True)
    time.sleep(hold)
    return drain(t, out, senders, timeout)


if __name__ == "__main__":
    sys.exit(main())
