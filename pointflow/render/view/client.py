"""The client end of one view: what the view server (per browser tab) and the notebook widget
both keep for a view of the render stage, with no I/O inside.

It holds the view's size, the credit last given, the newest frame number from render and
the camera of the last reply, and says what to send: ``credit`` (at most
:data:`~pointflow.render.view.protocol.MAX_CREDIT` frames in flight between credit and
display), and ``open`` again with the view's camera and a frame number past every frame
seen when the render stage restarted and answered that the view is gone
(:func:`~pointflow.render.view.protocol.is_gone`). Each method returns the messages
(``{"cmd": ..., ...}`` without the view's id) for the caller to send on its own socket.
"""
from __future__ import annotations

from typing import Any, Optional

from .protocol import MAX_CREDIT, is_gone

__all__ = ["ClientEnd"]


class ClientEnd:
    """One view's credit, frame numbers and camera, as the client sees them."""

    def __init__(self, width: int, height: int, granted: int = 0):
        self.width, self.height = width, height
        #: frames render may still send (credit given, not yet used); -1: none given yet
        self.granted = granted
        #: the newest frame number render sent: a view opened again numbers on from here
        self.seq_in = 0
        #: the camera of the render stage's last reply: a view opened again keeps it
        self.camera: Optional[dict] = None

    def open(self, again: bool = False, seen: int = 0) -> dict:
        """The ``open`` message; ``again`` after a render restart: with the camera and a frame
        number past every frame seen (``seen``: the caller's own newest, e.g. the last sent
        on), else the new stage's frames, numbered from 1, would be taken for old ones."""
        msg: dict[str, Any] = {"cmd": "open", "width": self.width, "height": self.height}
        if again:
            msg["seq"] = max(self.seq_in, seen, 0)
            if self.camera is not None:
                msg["state"] = {"camera": self.camera}
        return msg

    def resize(self, width: int, height: int) -> Optional[dict]:
        """The ``resize`` message when the size changed, else None."""
        if (width, height) == (self.width, self.height):
            return None
        self.width, self.height = width, height
        return {"cmd": "resize", "width": width, "height": height}

    def credit(self, in_flight: int, again: bool = False, withhold: bool = False) -> Optional[dict]:
        """The ``credit`` message (absolute: render sets the view's credit to ``n``): two less
        the frames not yet shown, none while ``withhold``; None when unchanged (``again``:
        say it anyway, so a lost one, or a restarted render stage, does not stall the view)."""
        n = 0 if withhold else max(0, MAX_CREDIT - in_flight)
        if n == self.granted and not again:
            return None
        self.granted = n
        return {"cmd": "credit", "n": n}

    def from_render(self, head: dict) -> str:
        """Note a message from render; returns what it is for the caller: ``frame``,
        ``gone`` (open the view again: :meth:`open` with ``again``), ``stats`` or ``other``
        (a reply, pick or error for the client)."""
        kind = head.get("type")
        if kind == "frame":
            self.granted = max(0, self.granted - 1)
            seq = head.get("seq")
            if isinstance(seq, int) and not isinstance(seq, bool):
                self.seq_in = max(self.seq_in, seq)
            return "frame"
        if is_gone(head):
            return "gone"
        if kind == "stats":
            return "stats"
        if kind == "reply" and isinstance(head.get("camera"), dict):
            self.camera = head["camera"]
        return "other"
