"""Run the real ingest stage (``stage_main``) in a spawned process, without the full
supervisor: the test owns the ring and binds the control/trace endpoints itself."""
from __future__ import annotations

import json
import multiprocessing as mp
import os
import shutil
import time
from typing import Any

import numpy as np
import zmq

from pointflow.config import load_config, new_run_dir
from pointflow.ring import PointRing
from pointflow.runtime.stage import RunInfo, stage_main


def base_config(**ring) -> dict:
    cfg = {"source": {"transport": "synthetic", "options": {"scans": 1, "realtime": False}},
           "ring": {"max_points": 200_000, **ring},
           "render": {"backend": "cpu", "color_by": "intensity", "output": {"dir": None}},
           "supervisor": {"heartbeat_ms": 50}}
    return cfg


def decode_spans(frames) -> list:
    """[trace_id, event, t0, t1, n] rows from a span batch (v1 JSON or v2 binary)."""
    head = json.loads(frames[0])
    if head.get("v") == 2:
        rows = np.frombuffer(frames[1], "<u8").reshape(-1, 5)
        return [[int(t), head["events"][int(e)], int(a), int(b), int(n)] for t, e, a, b, n in rows]
    return head["spans"]


class IngestStage:
    """A live ingest process plus the test's ends of its sockets."""

    def __init__(self, cfg: dict, ring_channels=None):
        self.cfg_dict = cfg
        self.cfg = load_config(cfg)
        imp = "importance" if (self.cfg.ring.importance_field or self.cfg.ring.eviction == "importance") else None
        self.ring = PointRing(self.cfg.ring.max_points, channels=ring_channels if ring_channels is not None else self.cfg.ring_channels(),
                              eviction=self.cfg.ring.eviction, importance_field=imp,
                              classification_weights=self.cfg.ring.classification_weights)
        self.run_dir = new_run_dir()
        self.endpoints = self.cfg.resolved_endpoints(self.run_dir)
        self.zctx = zmq.Context()
        self.control = self.zctx.socket(zmq.PULL)
        self.control.bind(self.endpoints.control)
        self.trace = self.zctx.socket(zmq.PULL)
        self.trace.bind(self.endpoints.trace)
        self.push = self.zctx.socket(zmq.PUSH)
        self.push.setsockopt(zmq.SNDHWM, 0)  # tests want every message delivered
        self.push.setsockopt(zmq.LINGER, 0)
        info = RunInfo(run_dir=self.run_dir, endpoints=self.endpoints, ring_name=self.ring.name,
                       slab_names=("", ""), out_dir=None, supervisor_pid=os.getpid())
        self.proc = mp.get_context("spawn").Process(
            target=stage_main, args=("ingest", "ingest", cfg, os.getcwd(), info), daemon=True)
        self.proc.start()
        self.push.connect(self.endpoints.ingest)
        self.last: dict[str, Any] = {}
        self.spans: list = []
        self.done = False

    def poll(self, timeout_ms: int = 100) -> None:
        if self.control.poll(timeout_ms):
            while True:
                try:
                    m = json.loads(self.control.recv(zmq.NOBLOCK))
                except zmq.Again:
                    break
                if m.get("type") == "heartbeat":
                    self.last = m["stats"]
                elif m.get("type") == "error":
                    raise AssertionError("ingest stage failed:\n" + m["message"])
        while True:
            try:
                frames = self.trace.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                break
            self.spans.extend(decode_spans(frames))

    def wait_stats(self, pred, timeout: float = 60.0) -> dict:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.poll()
            if self.last and pred(self.last):
                return self.last
            if not self.proc.is_alive():
                self.poll(0)
                raise AssertionError(f"ingest exited with {self.proc.exitcode}; last stats {self.last}")
        raise AssertionError(f"timed out; last stats {self.last}")

    def stop(self) -> dict:
        """SIGTERM, wait, return the final stats (the stage beats once more on exit)."""
        if self.proc.is_alive():
            self.proc.terminate()
        self.proc.join(20)
        self.poll(200)
        self.poll(50)
        return self.last

    def close(self) -> None:
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(5)
        for s in (self.push, self.control, self.trace):
            s.close(linger=0)
        self.zctx.term()
        self.ring.close()
        shutil.rmtree(self.run_dir, ignore_errors=True)
