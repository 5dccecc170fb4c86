"""Hand-made WebSocket clients for the view server's hostile-client tests and benchmark: a
client that never reads and frames written byte by byte, which a well-behaved library will
not produce (dora ships its test rig in the package the same way)."""
from __future__ import annotations

import base64
import os
import socket
import struct

__all__ = ["raw_websocket", "masked_frame"]


def raw_websocket(base: str, token: str, *, rcvbuf: int = 4096, wait_upgrade: bool = True,
                  timeout: float | None = None) -> socket.socket:
    """Open ``base``'s WebSocket (``http://host:port``) by hand with a tiny receive buffer and
    the token in the query (the cookie's name is per run: auth.cookie_name); with
    ``wait_upgrade`` read up to the end of the 101 answer (and check
    it), otherwise return at once without reading anything."""
    host, port = base.rsplit("//", 1)[1].split(":")
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    s.connect((host, int(port)))
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall((f"GET /ws?token={token} HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
               f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n").encode())
    if wait_upgrade:
        head = b""
        while b"\r\n\r\n" not in head:
            head += s.recv(1)
        if b" 101 " not in head.split(b"\r\n")[0]:
            raise ConnectionError(f"the view server did not upgrade: {head[:200]!r}")
    s.settimeout(timeout)
    return s


def masked_frame(data: bytes | str, opcode: int = 1) -> bytes:
    """One client-to-server WebSocket frame (masked, as RFC 6455 asks of clients)."""
    if isinstance(data, str):
        data = data.encode()
    mask = os.urandom(4)
    n = len(data)
    if n < 126:
        head = bytes([0x80 | opcode, 0x80 | n])
    elif n < 65536:
        head = bytes([0x80 | opcode, 0x80 | 126]) + struct.pack(">H", n)
    else:
        head = bytes([0x80 | opcode, 0x80 | 127]) + struct.pack(">Q", n)
    return head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data))
