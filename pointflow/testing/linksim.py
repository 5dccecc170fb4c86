"""A slow link on loopback: a TCP relay with a rate and a round-trip time, for the view
server's link tests and bench/bench_link.py (and for trying a view as a robot's Wi-Fi would
carry it: ``SlowLink(port, 10e6, 0.040)``).

Each direction is a bottleneck like a router's: bytes queue (at most ``buffer_bytes``;
beyond, the relay stops reading, so TCP's own backpressure reaches the sender, as a full
queue does), leave at ``rate_bps`` (a token bucket: each chunk takes ``len * 8 / rate``
seconds of the link), and arrive ``rtt_s / 2`` later (the propagation delay; it holds
no buffer). ``rate_bps=None`` and ``rtt_s=0`` relay as fast as loopback.
"""
from __future__ import annotations

import asyncio
import collections
import threading
from typing import Optional

__all__ = ["SlowLink"]

CHUNK = 16384


class _Pipe:
    """One direction: reader -> bottleneck queue -> paced sender -> delay line -> writer."""

    def __init__(self, reader, writer, rate_bps: Optional[float], delay_s: float, buffer_bytes: int, counts: dict,
                 key: str):
        self.reader, self.writer = reader, writer
        self.rate, self.delay, self.limit = rate_bps, delay_s, buffer_bytes
        self.queue: collections.deque = collections.deque()
        self.queued = 0
        self.room = asyncio.Event()
        self.room.set()
        self.have = asyncio.Event()
        self.eof = False
        self.counts, self.key = counts, key

    async def read(self) -> None:
        try:
            while True:
                await self.room.wait()
                data = await self.reader.read(CHUNK)
                if not data:
                    break
                self.queue.append(data)
                self.queued += len(data)
                if self.queued >= self.limit:
                    self.room.clear()
                self.have.set()
        except (ConnectionError, OSError):
            pass
        finally:
            self.eof = True
            self.have.set()

    async def pace(self) -> None:
        loop = asyncio.get_running_loop()
        t_free = loop.time()  # when the link has sent everything before
        try:
            while True:
                if not self.queue:
                    if self.eof:
                        break
                    self.have.clear()
                    await self.have.wait()
                    continue
                data = self.queue.popleft()
                now = loop.time()
                t_free = max(t_free, now) + (len(data) * 8.0 / self.rate if self.rate else 0.0)
                if t_free > now:
                    await asyncio.sleep(t_free - now)
                self.queued -= len(data)
                if self.queued < self.limit:
                    self.room.set()
                self.counts[self.key] = self.counts.get(self.key, 0) + len(data)
                if self.delay > 0:
                    loop.call_at(t_free + self.delay, self._deliver, data)
                else:
                    self._deliver(data)
            if self.delay > 0:
                await asyncio.sleep(self.delay)
        finally:
            try:
                self.writer.close()
            except Exception:  # noqa: BLE001 - the other end went first
                pass

    def _deliver(self, data: bytes) -> None:
        if not self.writer.is_closing():
            self.writer.write(data)


class SlowLink:
    """A relay from ``127.0.0.1:port`` (``.port`` once started) to ``host:target_port``, in a
    thread of its own. Use as a context manager."""

    def __init__(self, target_port: int, rate_bps: Optional[float] = None, rtt_s: float = 0.0, *,
                 buffer_bytes: Optional[int] = None, host: str = "127.0.0.1"):
        self.target = (host, int(target_port))
        self.rate = float(rate_bps) if rate_bps else None
        self.rtt = max(0.0, float(rtt_s))
        # a router's queue: the link's bytes in one round trip, at least 64 KiB
        bdp = int((self.rate or 0) / 8 * self.rtt)
        self.buffer = int(buffer_bytes) if buffer_bytes else max(65536, bdp)
        self.port = 0
        self.counts: dict = {}
        self._loop: Optional[asyncio.AbstractEventLoop] = None
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._run, name="pointflow-slowlink", daemon=True)
        self._server = None

    def __enter__(self) -> "SlowLink":
        self._thread.start()
        if not self._ready.wait(10):
            raise RuntimeError("the slow link did not start")
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self._loop is not None and self._loop.is_running():
            self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(5)

    def _run(self) -> None:
        loop = self._loop = asyncio.new_event_loop()
        asyncio.set_event_loop(loop)
        self._server = loop.run_until_complete(asyncio.start_server(self._conn, "127.0.0.1", 0))
        self.port = self._server.sockets[0].getsockname()[1]
        self._ready.set()
        try:
            loop.run_forever()
        finally:
            self._server.close()
            for t in asyncio.all_tasks(loop):
                t.cancel()
            loop.run_until_complete(asyncio.sleep(0))
            loop.close()

    async def _conn(self, c_reader, c_writer) -> None:
        try:
            s_reader, s_writer = await asyncio.open_connection(*self.target)
        except OSError:
            c_writer.close()
            return
        delay = self.rtt / 2
        up = _Pipe(c_reader, s_writer, self.rate, delay, self.buffer, self.counts, "up")
        down = _Pipe(s_reader, c_writer, self.rate, delay, self.buffer, self.counts, "down")
        await asyncio.gather(up.read(), up.pace(), down.read(), down.pace(), return_exceptions=True)
