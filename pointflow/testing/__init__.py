"""Test rigs shipped with the package (dora's ``testing.py`` is the model), apart from the
library code: here one stage in a spawned process without a supervisor, and the small
helpers tests and benchmarks share; :mod:`.serve` (hand-made WebSocket clients of the view
server) and :mod:`.rmw_zenoh_pub` (a publisher that behaves as ROS 2's rmw_zenoh) beside it.

:class:`StageRig` owns what the supervisor would: the ring, the run directory and the
control/trace endpoints the stage reports to; the stage itself is the real ``stage_main`` in
its own process. Tests drive it through its sockets; ``bench/`` times it.
"""
from __future__ import annotations

import contextlib
import json
import multiprocessing as mp
import os
import queue
import shutil
import socket
import subprocess
import sys
import threading
import time
from typing import Any, Callable, Sequence

import numpy as np
import zmq

from ..config import load_config, new_run_dir
from ..ring.config import build_ring
from ..stage.context import RunInfo
from ..runtime.stage import stage_main

__all__ = ["free_port", "wait_for", "decode_spans", "StageRig", "LineProc"]


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port nobody listens on right now (the OS picks it; a test binds it soon after)."""
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def wait_for(pred: Callable[[], Any], timeout: float = 30.0, interval: float = 0.05) -> Any:
    """``pred()``'s first true value, polled every ``interval`` s for up to ``timeout`` s; its
    last value (false) when time ran out (the caller asserts on it)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = pred()
        if v:
            return v
        time.sleep(interval)
    return pred()


def decode_spans(frames) -> list:
    """[trace_id, event, t0, t1, n] rows from a span batch (v1 JSON or v2 binary)."""
    head = json.loads(frames[0])
    if head.get("v") == 2:
        rows = np.frombuffer(frames[1], "<u8").reshape(-1, 5)
        return [[int(t), head["events"][int(e)], int(a), int(b), int(n)] for t, e, a, b, n in rows]
    return head["spans"]


class StageRig:
    """One live stage (``kind``, ``ingest`` by default) in a spawned process, plus the rig's
    ends of its control and trace sockets; ``last`` is its latest heartbeat's stats and
    ``spans`` the span rows it sent. The ring and slabs come from the ring package's builder,
    as the supervisor's do. Use as a context manager or call :meth:`close`."""

    def __init__(self, cfg: dict, kind: str = "ingest", *, name: str | None = None,
                 ring_channels: Sequence[str] | None = None, root: str | None = None,
                 log_level: int | None = None):
        self.cfg_dict = cfg
        self.cfg = load_config(cfg)
        self.kind = kind
        channels = list(ring_channels) if ring_channels is not None else self.cfg.ring_channels()
        self.ring, self.slabs = build_ring(self.cfg.ring, channels)
        self.run_dir = new_run_dir()
        self.endpoints = self.cfg.resolved_endpoints(self.run_dir)
        self.zctx = zmq.Context()
        self.control = self.zctx.socket(zmq.PULL)
        self.control.bind(self.endpoints.control)
        self.trace = self.zctx.socket(zmq.PULL)
        self.trace.bind(self.endpoints.trace)
        self._sockets = [self.control, self.trace]
        info = RunInfo(run_dir=self.run_dir, endpoints=self.endpoints, ring_name=self.ring.name,
                       slab_names=tuple(self.slabs.names), out_dir=None, supervisor_pid=os.getpid(),
                       **({} if log_level is None else {"log_level": log_level}))
        self.proc = mp.get_context("spawn").Process(
            target=stage_main, args=(name or kind, kind, cfg, root or os.getcwd(), info), daemon=True)
        self.proc.start()
        self.last: dict[str, Any] = {}
        self.spans: list = []

    def sender(self, endpoint: str | None = None) -> zmq.Socket:
        """A PUSH socket connected to the stage's input (``endpoints.ingest`` unless named) that
        keeps every message (no high-water mark) and is closed with the rig."""
        s = self.zctx.socket(zmq.PUSH)
        s.setsockopt(zmq.SNDHWM, 0)
        s.setsockopt(zmq.LINGER, 0)
        s.connect(endpoint or self.endpoints.ingest)
        self._sockets.append(s)
        return s

    def on_control(self, m: dict[str, Any]) -> None:
        """One control message: a heartbeat's stats become ``last``; a stage error raises
        AssertionError with the stage's message (a rig of more stages overrides this)."""
        if m.get("type") == "heartbeat":
            self.last = m["stats"]
        elif m.get("type") == "error":
            raise AssertionError(f"{m.get('stage', self.kind)} stage failed:\n" + m["message"])

    def poll(self, timeout_ms: int = 100) -> dict[str, Any]:
        """Read what the stage sent (control messages, spans); the latest stats."""
        if self.control.poll(timeout_ms):
            while True:
                try:
                    m = json.loads(self.control.recv(zmq.NOBLOCK))
                except zmq.Again:
                    break
                self.on_control(m)
        while True:
            try:
                frames = self.trace.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                break
            self.spans.extend(decode_spans(frames))
        return self.last

    def wait_stats(self, pred: Callable[[dict], bool], timeout: float = 60.0) -> dict:
        """The first heartbeat stats ``pred`` accepts; AssertionError if the stage exits or
        ``timeout`` passes first."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.poll()
            if self.last and pred(self.last):
                return self.last
            if not self.proc.is_alive():
                self.poll(0)
                raise AssertionError(f"{self.kind} exited with {self.proc.exitcode}; last stats {self.last}")
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
        for s in self._sockets:
            s.close(linger=0)
        self.zctx.term()
        for shm in (self.slabs, self.ring):
            shm.close()
            with contextlib.suppress(FileNotFoundError):
                shm.unlink()
        shutil.rmtree(self.run_dir, ignore_errors=True)

    def __enter__(self) -> "StageRig":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class LineProc:
    """A helper process whose stdout lines are read on a thread; closing its stdin ends it."""

    def __init__(self, args: list[str]):
        self.p = subprocess.Popen([sys.executable, *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True)
        self.lines: queue.Queue = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.p.stdout:
            self.lines.put(line.rstrip("\n"))

    def wait_line(self, prefix: str, timeout: float = 30.0) -> str:
        """The first line starting with ``prefix`` (lines read before are kept for later)."""
        for line in self.seen:
            if line.startswith(prefix):
                self.seen.remove(line)
                return line
        end = time.monotonic() + timeout
        while True:
            try:
                line = self.lines.get(timeout=max(0.01, end - time.monotonic()))
            except queue.Empty:
                raise AssertionError(f"no {prefix!r} line from {self.p.args} within {timeout} s; "
                                     f"seen {self.seen}; stderr: {self._stderr()}") from None
            if line.startswith(prefix):
                return line
            self.seen.append(line)

    def _stderr(self) -> str:
        if self.p.poll() is None:
            return "(running)"
        return self.p.stderr.read()[-2000:]

    def send(self, text: str) -> None:
        self.p.stdin.write(text)
        self.p.stdin.flush()

    def close(self) -> None:
        """Close its stdin (it exits), wait; kill it if it does not."""
        try:
            self.p.stdin.close()
        except OSError:
            pass
        try:
            self.p.wait(10)
        except subprocess.TimeoutExpired:
            self.p.kill()
            self.p.wait(5)
