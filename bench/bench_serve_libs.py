"""Which HTTP/WebSocket library the view server uses (issue 32 item 1): a measurement.

Each candidate serves one WebSocket on loopback in its own thread (its own event loop); the
client is the same for all (the ``websockets`` client in the main thread), so the numbers
differ only by the server:

* ``handshake`` — connect (HTTP upgrade) and close, median and p90 over ``--handshakes``;
* ``throughput`` — the server sends ``--messages`` binary messages of 200 KB (a 1280x720
  JPEG is ~100-250 KB) as fast as the client takes them: MB/s and messages/s;
* code size — lines of the server function below (the rest of the view server is the same).

Candidates: ``websockets`` (already a dependency), ``aiohttp``, and ``starlette`` on
``uvicorn`` (the ASGI stack rendercanvas's ``http`` backend runs on) when importable
(``pip install --target DIR starlette uvicorn`` and ``PYTHONPATH=DIR``). Rounds are
interleaved (A B C A B C ...), medians over rounds. The machine is shared: ``uptime``
before and after is written with the results.

    .venv/bin/python bench/bench_serve_libs.py              # ~1 min
Writes ``bench/results/serve_libs.json``.
"""
from __future__ import annotations

import argparse
import asyncio
import inspect
import json
import socket
import statistics
import threading
import time
from pathlib import Path

import _harness as harness

import websockets

PAYLOAD = bytes(range(256)) * 800  # 204,800 bytes


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# --------------------------------------------------------------------------- servers
def serve_websockets(port: int, ready: threading.Event, stop: threading.Event) -> None:
    async def handler(ws):
        async for msg in ws:
            n = int(msg)
            for _ in range(n):
                await ws.send(PAYLOAD)

    async def run():
        async with websockets.serve(handler, "127.0.0.1", port, max_size=2**20):
            ready.set()
            while not stop.is_set():
                await asyncio.sleep(0.05)

    asyncio.run(run())


def serve_aiohttp(port: int, ready: threading.Event, stop: threading.Event) -> None:
    from aiohttp import web

    async def ws_handler(request):
        ws = web.WebSocketResponse(max_msg_size=2**20)
        await ws.prepare(request)
        async for msg in ws:
            for _ in range(int(msg.data)):
                await ws.send_bytes(PAYLOAD)
        return ws

    async def run():
        app = web.Application()
        app.router.add_get("/", ws_handler)
        runner = web.AppRunner(app, access_log=None)
        await runner.setup()
        await web.TCPSite(runner, "127.0.0.1", port).start()
        ready.set()
        while not stop.is_set():
            await asyncio.sleep(0.05)
        await runner.cleanup()

    asyncio.run(run())


def serve_starlette(port: int, ready: threading.Event, stop: threading.Event) -> None:
    import uvicorn
    from starlette.applications import Starlette
    from starlette.routing import WebSocketRoute

    async def ws_handler(ws):
        await ws.accept()
        while True:
            try:
                n = int(await ws.receive_text())
            except Exception:  # noqa: BLE001 - the client left
                return
            for _ in range(n):
                await ws.send_bytes(PAYLOAD)

    app = Starlette(routes=[WebSocketRoute("/", ws_handler)])
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="error", ws="websockets-sansio"))

    async def run():
        task = asyncio.ensure_future(server.serve())
        while not server.started:
            await asyncio.sleep(0.01)
        ready.set()
        while not stop.is_set():
            await asyncio.sleep(0.05)
        server.should_exit = True
        await task

    asyncio.run(run())


CANDIDATES = {"websockets": serve_websockets, "aiohttp": serve_aiohttp, "starlette+uvicorn": serve_starlette}


# --------------------------------------------------------------------------- client
async def measure(port: int, handshakes: int, messages: int) -> dict:
    url = f"ws://127.0.0.1:{port}/"
    hs = []
    for _ in range(handshakes):
        t0 = time.perf_counter()
        async with websockets.connect(url, max_size=2**20):
            pass
        hs.append((time.perf_counter() - t0) * 1e3)
    async with websockets.connect(url, max_size=2**20) as ws:
        await ws.send("5")  # warm up
        for _ in range(5):
            await ws.recv()
        t0 = time.perf_counter()
        await ws.send(str(messages))
        got = 0
        for _ in range(messages):
            got += len(await ws.recv())
        dt = time.perf_counter() - t0
    hs.sort()
    return {"handshake_ms_p50": statistics.median(hs), "handshake_ms_p90": hs[int(len(hs) * 0.9)],
            "messages_per_s": messages / dt, "mb_per_s": got / dt / 1e6}


def one_round(name: str, handshakes: int, messages: int) -> dict:
    port = _free_port()
    ready, stop = threading.Event(), threading.Event()
    t = threading.Thread(target=CANDIDATES[name], args=(port, ready, stop), daemon=True)
    t.start()
    if not ready.wait(20):
        raise RuntimeError(f"{name} did not start")
    try:
        return asyncio.run(measure(port, handshakes, messages))
    finally:
        stop.set()
        t.join(10)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--handshakes", type=int, default=100)
    ap.add_argument("--messages", type=int, default=300)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "serve_libs.json"))
    a = ap.parse_args()
    names = []
    for n in CANDIDATES:
        try:
            if n == "aiohttp":
                import aiohttp  # noqa: F401
            elif n.startswith("starlette"):
                import starlette  # noqa: F401
                import uvicorn  # noqa: F401
            names.append(n)
        except ImportError:
            print(f"{n}: not installed, skipped")
    mach = harness.machine()
    up0 = mach["uptime_before"]
    runs: dict[str, list[dict]] = {n: [] for n in names}
    for r in range(a.rounds):
        for n in names:
            runs[n].append(one_round(n, a.handshakes, a.messages))
    harness.machine_done(mach)
    up1 = mach["uptime_after"]
    out = {"command": harness.command(), "machine": mach, "uptime_before": up0, "uptime_after": up1,
           "payload_bytes": len(PAYLOAD), "rounds": a.rounds,
           "results": {}}
    for n in names:
        med = {k: round(statistics.median(x[k] for x in runs[n]), 3) for k in runs[n][0]}
        med["server_code_lines"] = len(inspect.getsource(CANDIDATES[n]).splitlines())
        out["results"][n] = med
        print(f"{n:18s} handshake p50 {med['handshake_ms_p50']:.2f} ms p90 {med['handshake_ms_p90']:.2f} ms  "
              f"{med['messages_per_s']:.0f} msg/s {med['mb_per_s']:.0f} MB/s  server {med['server_code_lines']} lines")
    print(up0, "\n", up1, sep="")
    harness.write_result(a.out, out, indent=1)


if __name__ == "__main__":
    main()
