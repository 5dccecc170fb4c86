"""Who may open the page and the WebSocket: the token (in the URL once, then an HttpOnly
cookie) and the WebSocket's Origin. Pure functions, so the refusals are tested without a
server and the messages are the same everywhere."""
from __future__ import annotations

import hmac
import os
import secrets
from typing import Optional
from urllib.parse import urlsplit

COOKIE = "pointflow_view"


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
