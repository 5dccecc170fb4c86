"""The sender stage of ``pointflow send``: the loop of the configured engine
(``send.engine``: :mod:`.sender` for ZeroMQ, :mod:`.zenoh_sender` for Zenoh)."""
from __future__ import annotations


def main(ctx) -> None:
    """Stage loop (``pointflow.runtime.stage.STAGE_MAINS['sender']``)."""
    if ctx.cfg.send.engine == "zenoh":
        from .zenoh_sender import main as zenoh_main

        zenoh_main(ctx)
    else:
        from .sender import main as zmq_main

        zmq_main(ctx)
