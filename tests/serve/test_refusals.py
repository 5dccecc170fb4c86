"""Refusals (issue 32): no token, a wrong token, a foreign Origin, a file that is not the
page's, a non-loopback address without TLS or ``insecure``: each refused with its one-line
message and counted, and the pipeline goes on drawing."""
from __future__ import annotations

import os
import re
import subprocess
import sys
import time
import urllib.error

import pytest

from pointflow import Pipeline

from .helpers import TOKEN, base_url, config, cookie_header, http_get, serve_stats, synthetic_source, ws_connect


@pytest.fixture(scope="module")
def pipe(tmp_path_factory):
    with Pipeline.from_dict(config(synthetic_source()), out_dir=str(tmp_path_factory.mktemp("refusals"))) as p:
        base_url(p)
        yield p


def _frames(pipe) -> int:
    return pipe.stats()["stages"]["render"].get("frames", 0)


def test_page_needs_the_token_then_a_cookie(pipe):
    base = base_url(pipe)
    code, body, _ = http_get(base + "/")
    assert code == 403 and "a token is required" in body and "Traceback" not in body
    code, body, _ = http_get(base + "/?token=not-the-right-token-000")
    assert code == 403 and "wrong token" in body
    code, body, _ = http_get(base + "/view.js")  # the page's files too
    assert code == 403
    code, _, headers = http_get(f"{base}/?token={TOKEN}")
    assert code == 303 and headers["Location"] == "/"  # the token leaves the address bar
    cookie = headers["Set-Cookie"]
    port = base.rsplit(":", 1)[1]
    assert re.match(rf"pointflow_view_{port}_[0-9a-f]{{10}}={TOKEN};", cookie), cookie  # per run and port
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie
    code, body, _ = http_get(base + "/", {"Cookie": cookie_header(base)})
    assert code == 200 and "view.js" in body
    code, body, _ = http_get(base + "/view.js", {"Cookie": cookie_header(base)})
    assert code == 200 and "WebSocket" in body
    pipe.wait(10, until=lambda: serve_stats(pipe)["refused_token"] >= 3)  # counts come with the next heartbeat
    assert serve_stats(pipe)["refused_token"] >= 3


@pytest.mark.parametrize("path", ["/config.py", "/../../etc/passwd", "/static/../server.py", "/%2e%2e/auth.py",
                                  "/__init__.py", "/static/index.html"])
def test_only_the_pages_own_files_are_served(pipe, path):
    base = base_url(pipe)
    code, body, _ = http_get(base + path, {"Cookie": cookie_header(base)})
    assert code == 404, (path, code)
    assert "import" not in body


def test_websocket_refusals_and_the_pipeline_goes_on(pipe):
    from websockets.exceptions import InvalidStatus

    base = base_url(pipe)
    before = serve_stats(pipe)
    f0 = _frames(pipe)
    for kw, why in (({"token": None}, "a token is required"), ({"token": "wrong-token-00000000000"}, "wrong token"),
                    ({"origin": "http://evil.example"}, "origin http://evil.example is not allowed")):
        with pytest.raises(InvalidStatus) as exc:
            ws_connect(base, **kw)
        assert exc.value.response.status_code == 403
        assert why in exc.value.response.body.decode()
    # the page's own origin is fine, and so is a client without Origin (not a browser page; it has the token)
    with ws_connect(base) as ws:
        assert '"hello"' in ws.recv(timeout=20)
    with ws_connect(base, origin=None) as ws:
        assert '"hello"' in ws.recv(timeout=20)
    pipe.wait(10, until=lambda: serve_stats(pipe)["refused_origin"] > before["refused_origin"])
    pipe.wait(1.0)
    after = serve_stats(pipe)
    assert after["refused_token"] - before["refused_token"] == 2
    assert after["refused_origin"] - before["refused_origin"] == 1
    pipe.wait(30, until=lambda: _frames(pipe) > f0 + 3)
    assert _frames(pipe) > f0 + 3, "the render stage stopped drawing"
    assert after.get("restarts", 0) == 0 and pipe.stats()["stages"]["render"].get("restarts", 0) == 0


def _cli(tmp_path, *args, timeout=120):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [os.getcwd(), os.environ.get("PYTHONPATH")])))
    cfg = tmp_path / "p.yaml"
    cfg.write_text("sources:\n  - name: lidar\n    transport: synthetic\n    options: {scan_hz: 10, points_per_scan: 2000}\n"
                   "render: {backend: cpu, size: [64, 48], output: {every_n_frames: 100000}}\n")
    return subprocess.Popen([sys.executable, "-m", "pointflow.cli", "run", str(cfg), "--out", str(tmp_path / "out"),
                             "-q", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def test_non_loopback_without_tls_is_refused_at_load(tmp_path):
    p = _cli(tmp_path, "--serve", "0.0.0.0:0", "--duration", "5")
    out, err = p.communicate(timeout=120)
    assert p.returncode != 0
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "serve.insecure" in lines[0] and "serve.tls.cert" in lines[0], err
    assert "Traceback" not in err


def test_cli_prints_the_view_line_and_it_opens(tmp_path):
    p = _cli(tmp_path, "--serve", "127.0.0.1:0", "--duration", "60")
    try:
        url = None
        for line in p.stderr:
            m = re.match(r"view: (http://127\.0\.0\.1:\d+/\?token=[A-Za-z0-9_-]+)$", line.strip())
            if m:
                url = m.group(1)
                break
        assert url, "no view: line"
        code, _, headers = http_get(url)
        assert code == 303 and "HttpOnly" in headers["Set-Cookie"]
        code, body, _ = http_get(url.split("?")[0] + "?token=" + "x" * 20)
        assert code == 403 and "wrong token" in body
    finally:
        p.terminate()
        p.communicate(timeout=60)
    assert p.returncode == 0


def test_a_killed_view_server_comes_back_on_the_same_url(pipe):
    """A fault in the web server ends only its stage: the supervisor restarts it on the same
    port with the same token, and the render stage never noticed."""
    import signal

    base = base_url(pipe)
    st = serve_stats(pipe)
    r0 = pipe.stats()["stages"]["render"]
    os.kill(st["pid"], signal.SIGKILL)
    pipe.wait(60, until=lambda: serve_stats(pipe).get("restarts", 0) >= 1 and serve_stats(pipe).get("alive")
              and serve_stats(pipe).get("pid") != st["pid"])
    assert serve_stats(pipe)["restarts"] >= 1
    code = None
    end = time.monotonic() + 60
    while time.monotonic() < end:
        try:
            code, body, _ = http_get(base + "/", {"Cookie": cookie_header(base)})
            break
        except OSError:
            pipe.wait(0.5)
    assert code == 200, "the restarted view server is not on the same URL"
    with ws_connect(base) as ws:
        assert '"hello"' in ws.recv(timeout=20)
    r1 = pipe.stats()["stages"]["render"]
    assert r1["restarts"] == r0["restarts"] and r1["pid"] == r0["pid"]


def test_tls(tmp_path):
    """serve.tls: https and wss with the certificate of `pointflow keys NAME --tls`; the
    cookie is Secure."""
    import ssl

    from pointflow.remote.tls import make_certificate

    make_certificate("view", tmp_path, hosts=["127.0.0.1", "localhost"])
    cfg = config(synthetic_source(), serve={"tls": {"cert": str(tmp_path / "view.pem"),
                                                    "key": str(tmp_path / "view-key.pem")}})
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path / "out")) as p:
        port = base_url(p).rsplit(":", 1)[1]
        ctx = ssl.create_default_context(cafile=str(tmp_path / "ca.pem"))
        import urllib.request

        class NoRedirect(urllib.request.HTTPRedirectHandler):
            def redirect_request(self, *a, **k):
                return None

        opener = urllib.request.build_opener(urllib.request.HTTPSHandler(context=ctx), NoRedirect)
        try:
            opener.open(f"https://127.0.0.1:{port}/?token={TOKEN}", timeout=20)
            raise AssertionError("expected a redirect")
        except urllib.error.HTTPError as e:
            assert e.code == 303 and "Secure" in e.headers["Set-Cookie"]
        with pytest.raises(OSError):  # plain http on the TLS port gets nowhere
            urllib.request.urlopen(f"http://127.0.0.1:{port}/?token={TOKEN}", timeout=10).read()
        from websockets.sync.client import connect

        with connect(f"wss://127.0.0.1:{port}/ws?token={TOKEN}", ssl=ctx, origin=f"https://127.0.0.1:{port}",
                     open_timeout=20) as ws:
            assert '"hello"' in ws.recv(timeout=20)


def test_one_client_too_many_is_refused(tmp_path):
    from websockets.exceptions import InvalidStatus

    cfg = config(synthetic_source(), serve={"limits": {"max_clients": 2}})
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as p:
        base = base_url(p)
        a, b = ws_connect(base), ws_connect(base)
        for ws in (a, b):
            assert '"hello"' in ws.recv(timeout=20)
        with pytest.raises(InvalidStatus) as exc:
            ws_connect(base)
        assert exc.value.response.status_code == 503 and "serve.limits.max_clients" in exc.value.response.body.decode()
        a.close()
        p.wait(20, until=lambda: serve_stats(p).get("clients", 2) < 2)
        with ws_connect(base) as c:  # a place came free
            assert '"hello"' in c.recv(timeout=20)
        b.close()
        p.wait(10, until=lambda: serve_stats(p).get("refused_full", 0) >= 1)
        assert serve_stats(p)["refused_full"] == 1
