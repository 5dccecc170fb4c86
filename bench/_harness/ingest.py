"""The ingest stage under measurement: the package's one-stage rig
(``pointflow.testing.StageRig``) fed by a producer process, timed from the start
signal to the ring push that completed the count (bench_ingest.py, bench_frames.py)."""
from __future__ import annotations

import multiprocessing as mp
import time

import numpy as np
import zmq

from pointflow.testing import StageRig

from . import cpu_seconds

#: ``frames.fixed`` with a static chain: every chunk placed in the fixed frame at ingest
#: (the issue-20 target with frames on: >= 0.85 of the frames-off figure)
FRAMES_ON = {"fixed": "odom", "static": [{"parent": "odom", "child": "lidar", "translation": [3.0, -2.0, 1.7],
                                          "rpy_deg": [1.0, 2.0, 30.0]}]}


def chunk(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """n float32 xyz positions and intensities."""
    rng = np.random.default_rng(seed)
    return rng.uniform(-100, 100, (n, 3)).astype(np.float32), rng.uniform(0, 255, n).astype(np.float32)


def wire_producer(endpoint: str, n: int, count: int, go, ready=None, frame_id: str = "", stamp0: int = 0) -> None:
    """A process sending ``count`` n-point chunks with ``wire.send`` once ``go`` is set
    (stamped ``stamp0 + i us`` when ``stamp0`` is given)."""
    from pointflow import wire
    from pointflow.chunk import PointChunk

    pos, inten = chunk(n, 1)
    ctx = zmq.Context()
    s = ctx.socket(zmq.PUSH)
    s.setsockopt(zmq.SNDHWM, 64)
    s.connect(endpoint)
    if ready is not None:
        ready.set()
    go.wait()
    for i in range(count):
        stamp = {"stamp_ns": stamp0 + i * 1000} if stamp0 else {}
        wire.send(s, PointChunk(positions=pos, channels={"intensity": inten}, source_id="bench", seq=i, trace_id=0,
                                frame_id=frame_id, **stamp))
    s.close(linger=-1)
    ctx.term()


class IngestRun:
    """The real ingest stage in its own process (the package's rig), fed by a producer
    process; ``frames`` adds a ``frames:`` block (bench_frames.py)."""

    def __init__(self, cap: int, frames: dict | None = None):
        import psutil

        self.cfg_dict = {"source": {"transport": "synthetic"}, "ring": {"max_points": cap},
                         "render": {"color_by": "intensity", "output": {"dir": None}},
                         "tracing": {"enabled": False}, "supervisor": {"heartbeat_ms": 20}}
        if frames:
            self.cfg_dict["frames"] = frames
        self.rig = StageRig(self.cfg_dict, "ingest", log_level=40)
        self.ring, self.ep = self.rig.ring, self.rig.endpoints
        self.ps = psutil.Process(self.rig.proc.pid)
        #: points per CPU-second of the ingest process in the last measure() (its own cost,
        #: independent of how busy the shared machine is)
        self.cpu_rate = 0.0
        #: the heartbeat-timed rate of the last measure()
        self.hb_rate = 0.0

    @property
    def last(self) -> dict:
        return self.rig.last

    def stats(self, timeout_ms=100) -> dict:
        return self.rig.poll(timeout_ms)

    def measure(self, n: int, count: int, frame_id: str = "", stamp0: int = 0) -> float:
        """Points/s of ``count`` n-point chunks, from the start signal to the ring push that
        completed the count (``hb_rate``: to the heartbeat that showed them all)."""
        ctx = mp.get_context("spawn")
        go, ready = ctx.Event(), ctx.Event()
        before = self.stats(2000).get("points_out", 0)
        while not self.last:
            before = self.stats(200).get("points_out", 0)
        prod = ctx.Process(target=wire_producer, args=(self.ep.ingest, n, count, go, ready, frame_id, stamp0),
                           daemon=True)
        prod.start()
        ready.wait(60)
        time.sleep(0.1)
        from pointflow.ring.ring import I_LAST_PUSH_NS, I_TOTAL_WRITTEN

        st = self.ring._st  # the ring's shared header (read-only here; an int64 read is atomic)
        w0 = int(st[I_TOTAL_WRITTEN])
        c0 = cpu_seconds(self.ps)
        t_go = time.perf_counter()
        go.set()
        # ends: the time of the ring push that completed the count (the ring's header keeps the
        # CLOCK_MONOTONIC time of its last push, taken as that push starts: one push, well
        # under 1 ms, early), and when a heartbeat shows every point accounted for (up to a
        # heartbeat interval later: the way this bench timed pointflow before)
        t_ring = t_hb = None
        target = before + n * count
        deadline = time.monotonic() + 600
        while time.monotonic() < deadline and t_hb is None:
            s = self.stats(5)
            now = time.perf_counter()
            if t_ring is None and int(st[I_TOTAL_WRITTEN]) - w0 >= n * count:
                t_ring = int(st[I_LAST_PUSH_NS]) / 1e9  # perf_counter is CLOCK_MONOTONIC too
            if s.get("points_out", 0) + sum(s.get("drops", {}).values()) >= target:
                t_hb = now
        c1 = cpu_seconds(self.ps)
        prod.join()
        self.cpu_rate = n * count / max(1e-9, c1 - c0)
        self.hb_rate = n * count / (t_hb - t_go)
        return n * count / ((t_ring or t_hb) - t_go)

    def close(self) -> dict:
        self.rig.proc.terminate()
        self.rig.proc.join(10)
        final = self.stats(300)
        self.rig.close()
        return final
