"""The sender stage of ``pointflow send``: the loop of the configured engine
(``send.engine``: :mod:`.sender` for ZeroMQ, :mod:`.zenoh_sender` for Zenoh)."""
from __future__ import annotations

from ..stage.kinds import StageKind, register_stage_kind

#: ``pointflow send``: binds the socket the sources push to, so they start once it
#: reported in (a short replay is not over before anyone listens).
KIND = register_stage_kind(StageKind(
    name="sender", main="pointflow.remote.process:main", start_order=35, stop_wave=1, roles=("send",),
    await_ready=True, counters=("rejected_messages",), accounting="pointflow.remote.accounting:send_identities"))


def main(ctx) -> None:
    """Stage loop (:data:`KIND`)."""
    if ctx.cfg.send.engine == "zenoh":
        from .zenoh_sender import main as zenoh_main

        zenoh_main(ctx)
    else:
        from .sender import main as zmq_main

        zmq_main(ctx)
