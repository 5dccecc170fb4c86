"""Who may open the page and the WebSocket: the token (in the URL once, then an HttpOnly
cookie) and the WebSocket's Origin. Pure functions, so the refusals are tested without a
server and the messages are the same everywhere."""
from __future__ import annotations

import functools
import hashlib
import hmac
import ipaddress
import os
import secrets
from typing import Optional
from urllib.parse import urlsplit

#: The cookie's name starts so; the rest is the port and the run (:func:`cookie_name`).
COOKIE = "pointflow_view"


def cookie_name(port: int, run_dir: str) -> str:
    """The token cookie's name for this run and port: browsers keep cookies per host name,
    not per port, so two runs on one host (or a run and its successor on the same port)
    must not overwrite each other's cookie."""
    return f"{COOKIE}_{int(port)}_{hashlib.sha256(run_dir.encode()).hexdigest()[:10]}"


@functools.lru_cache(maxsize=1)
def machine_names() -> frozenset:
    """This machine's names, looked up once: ``getfqdn`` may ask DNS, which must not happen
    per request inside the event loop (a junk Host header would stall every view)."""
    import socket

    return frozenset(n.lower() for n in (socket.gethostname(), socket.getfqdn()) if n)


def check_host(host_header: Optional[str], bound_host: str, allowed: list[str]) -> Optional[str]:
    """None when a request's ``Host`` may be served, else the reason (a DNS-rebinding page
    reaches the server under its own name: ``evil.example:PORT``). Served: an IP address (it
    cannot be rebound), ``localhost``, the address the server is bound to, this machine's
    name when it listens on every address, and ``serve.allowed_hosts`` (``name`` or
    ``name:port``, e.g. a reverse proxy's)."""
    if not host_header:
        return "a request without a Host header is not served"
    h = host_header.strip().lower()
    try:
        u = urlsplit(f"//{h}")
        name, port = (u.hostname or ""), u.port
    except ValueError:
        return f"host {host_header[:80]!r} is not allowed"
    for a in allowed:
        a = a.lower()
        if a == name or (port is not None and a == f"{name}:{port}") or a == h:
            return None
    if name == "localhost" or name == bound_host.strip("[]").lower():
        return None
    try:
        ipaddress.ip_address(name)
        return None
    except ValueError:
        pass
    if bound_host in ("0.0.0.0", "::", "") and name in machine_names():
        return None
    return (f"host {host_header[:80]!r} is not allowed (an IP address, localhost, this machine's name or "
            "serve.allowed_hosts)")


def new_token() -> str:
    return secrets.token_urlsafe(24)


def run_token(run_dir: str, configured: Optional[str]) -> str:
    """The run's token: the configured one, or a random one kept in the (0700) run
    directory, so a restarted view server keeps the token (and the cookies) of the run."""
    if configured:
        return configured
    path = os.path.join(run_dir, "serve-token")
    try:
        with open(path) as f:
            tok = f.read().strip()
            if tok:
                return tok
    except FileNotFoundError:
        pass
    tok = new_token()
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(tok)
    return tok


def token_ok(given: Optional[str], token: str) -> bool:
    return bool(given) and hmac.compare_digest(given.encode(), token.encode())


def check_token(query_token: Optional[str], cookie_token: Optional[str], token: str) -> Optional[str]:
    """None when allowed, else the one-line reason for the 403."""
    if token_ok(query_token, token) or token_ok(cookie_token, token):
        return None
    if query_token or cookie_token:
        return "wrong token: open the view: URL the pipeline printed (the token changes with each run)"
    return "a token is required: open the view: URL the pipeline printed (…/?token=…)"


def check_origin(origin: Optional[str], host_header: Optional[str], scheme: str, allowed: list[str]) -> Optional[str]:
    """None when a WebSocket from ``origin`` may connect, else the reason. Browsers always
    send Origin; a page of another site (which could carry the cookie) is refused. A client
    without Origin is not a browser page: it still needs the token."""
    if origin is None:
        return None
    o = origin.rstrip("/").lower()
    if host_header and o == f"{scheme}://{host_header}".lower():
        return None
    if any(o == a.rstrip("/").lower() for a in allowed):
        return None
    # the same host on loopback under another name (localhost vs 127.0.0.1) is the same machine's page
    try:
        u, h = urlsplit(o), urlsplit(f"{scheme}://{host_header or ''}")
        loop = ("localhost", "127.0.0.1", "::1")
        if u.scheme == scheme and u.hostname in loop and h.hostname in loop and u.port == h.port:
            return None
    except ValueError:
        pass
    return f"origin {origin} is not allowed (only the page's own origin{' and serve.allowed_origins' if allowed else ''})"
