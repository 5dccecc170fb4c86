"""A ROS 2 viewer in one process: the real ``ros2_zenoh`` transport (as a pipeline's source
stage runs it, INFO lines logged), read until ``max_chunks`` clouds came or the timeout;
writes the transport's counters (OUT.json) and every received position (OUT.npy).

Usage: python ros2_zenoh_probe.py OPTIONS_JSON OUT_PREFIX TIMEOUT_S
"""
from __future__ import annotations

import json
import logging
import sys
import time

import numpy as np

from pointflow.ingest.transports.ros2_zenoh import Ros2ZenohTransport


def main() -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    opts, out, timeout = json.loads(sys.argv[1]), sys.argv[2], float(sys.argv[3])
    t = Ros2ZenohTransport(Ros2ZenohTransport.validate_options(opts, "options", "."), "viewer")
    clouds = []
    try:
        t.open()
        print("probe: open", flush=True)
        end = time.monotonic() + timeout
        it = t.chunks()
        while time.monotonic() < end:
            try:
                c = next(it)
            except StopIteration:  # max_chunks reached
                break
            if c is not None:
                clouds.append(np.asarray(c.positions, dtype=np.float64))
    finally:
        t.close()
        with open(out + ".json", "w") as f:
            json.dump(t.counters, f)
        np.save(out + ".npy", np.concatenate(clouds) if clouds else np.zeros((0, 3)))
    print(f"probe: done, {len(clouds)} clouds", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
