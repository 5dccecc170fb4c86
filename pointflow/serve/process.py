"""The view server stage: its own process (a fault in a client or in the web server never
stops the render stage). An asyncio loop in the main thread runs the web server
(:mod:`.server`); a small task beats the heartbeat and watches for the stop."""
from __future__ import annotations

import asyncio
import dataclasses
import os
import sys

from ..stage.kinds import StageKind, register_stage_kind


def wanted(cfg) -> bool:
    """A run has a view server with a ``serve:`` block (or ``--serve``)."""
    return cfg.serve is not None


#: Nothing connects to it, so it may start late; it stops with ingest (wave 1), before the
#: render stage, so its views are closed while render still answers.
KIND = register_stage_kind(StageKind(
    name="serve", main="pointflow.serve.process:main", start_order=40, stop_wave=1,
    counters=("clients_total", "refused_token", "refused_origin", "refused_full", "bad_messages", "rate_limited",
              "send_timeouts", "frames_in", "frames_sent", "dropped_frames", "bytes_sent", "encode_errors",
              "control_sent", "control_dropped", "render_errors", "clients_gone", "client_errors", "server_errors",
              "bogus_acks", "dropped_messages", "refused_host", "header_timeouts", "views_reopened",
              "credit_withheld"),
    wanted="pointflow.serve.process:wanted"))


def _playback_endpoints(cfg, base: str) -> dict[str, str]:
    """Replaying sources (file, rosbag) -> their playback endpoints (as Pipeline.playback)."""
    from ..ingest.playback import playback_endpoint
    from ..ingest.transports import resolve_transport

    out = {}
    for i, s in enumerate(cfg.sources):
        try:
            seekable = getattr(resolve_transport(s.transport), "seekable", False)
        except Exception:  # noqa: BLE001 - an unknown transport is refused elsewhere
            seekable = False
        if not s.external and seekable:
            out[s.name] = playback_endpoint(base, i)
    return out


async def _run(ctx) -> None:
    from ..render.view.protocol import COLORMAPS, color_by_options
    from .auth import run_token
    from .server import ViewServer

    sc = ctx.cfg.serve
    token = run_token(ctx.info.run_dir, sc.token)
    port_file = os.path.join(ctx.info.run_dir, "serve-port")
    if sc.port == 0 and ctx.info.restart_count > 0 and os.path.exists(port_file):
        with open(port_file) as f:  # a restarted server keeps the URL the user has open
            sc = dataclasses.replace(sc, port=int(f.read().strip() or 0))
    srv = ViewServer(sc, views_endpoint=ctx.endpoints.views,
                     playback_endpoints=_playback_endpoints(ctx.cfg, ctx.endpoints.playback), token=token,
                     zctx=ctx.zmq, counters=ctx.counters, spans=ctx.spans,
                     sources=[s.name for s in ctx.cfg.sources],
                     color_by=color_by_options(ctx.cfg.ring_channels()), colormaps=list(COLORMAPS), run_dir=ctx.info.run_dir)
    try:
        url = await srv.start()
    except OSError as exc:  # the port is taken or the address is not this host's: restarting cannot help
        ctx.fail_run(f"serve: cannot listen on {sc.host}:{sc.port}: {exc.strerror or exc} "
                     "(set serve.port, or --serve [HOST:]PORT; 0 = any free port)")
        return
    with open(port_file, "w") as f:
        f.write(str(srv.port))
    if ctx.info.restart_count == 0:
        print(f"view: {url}", file=sys.stderr, flush=True)
    else:
        ctx.log.info("view server restarted; the view: URL is unchanged")
    ctx.on_beat.append(srv.update_stats)
    try:
        while ctx.running:
            ctx.beat()
            await asyncio.sleep(0.05)
    finally:
        await srv.stop()


def main(ctx) -> None:
    """Stage loop (the ``serve`` kind's ``main``)."""
    asyncio.run(_run(ctx))
