"""The ``serve:`` block and ``--serve`` checked at load; the token and Origin rules."""
from __future__ import annotations

import pytest

from pointflow.config import ConfigError, load_config
from pointflow.serve.auth import check_origin, check_token, run_token
from pointflow.serve.config import parse_serve_arg, with_serve

SRC = {"transport": "synthetic"}


def _load(serve, tmp_path=None):
    return load_config({"source": SRC, "serve": serve}, base_dir=str(tmp_path) if tmp_path else None)


def test_defaults_are_loopback_with_a_random_token():
    sc = _load({}).serve
    assert sc.host == "127.0.0.1" and sc.token is None and sc.tls is None and not sc.insecure
    assert load_config({"source": SRC}).serve is None  # no block: no view server


@pytest.mark.parametrize("host", ["0.0.0.0", "192.168.1.20", "::", "robot.local"])
def test_non_loopback_needs_tls_or_insecure(host):
    with pytest.raises(ConfigError) as exc:
        _load({"host": host})
    assert exc.value.path == "serve.insecure"
    assert "serve.tls.cert" in str(exc.value) and "\n" not in str(exc.value)
    assert _load({"host": host, "insecure": True}).serve.insecure


@pytest.mark.parametrize("host", ["127.0.0.1", "localhost", "::1", "127.0.0.2"])
def test_loopback_needs_nothing(host):
    assert _load({"host": host}).serve.host == host


def test_tls_files_are_checked_and_resolved(tmp_path):
    from pointflow.remote.tls import make_certificate

    with pytest.raises(ConfigError) as exc:
        _load({"host": "0.0.0.0", "tls": {"cert": "nope.pem", "key": "nope-key.pem"}}, tmp_path)
    assert exc.value.path == "serve.tls.cert" and "no such file" in str(exc.value)
    with pytest.raises(ConfigError) as exc:
        _load({"host": "0.0.0.0", "tls": {"cert": "x.pem"}}, tmp_path)
    assert exc.value.path == "serve.tls.cert"
    make_certificate("view", tmp_path, hosts=["127.0.0.1"])
    sc = _load({"host": "0.0.0.0", "tls": {"cert": "view.pem", "key": "view-key.pem"}}, tmp_path).serve
    assert sc.tls.cert == str(tmp_path / "view.pem")


@pytest.mark.parametrize("block,key", [({"token": "short"}, "serve.token"), ({"port": 70000}, "serve.port"),
                                       ({"limits": {"queue_frames": 0}}, "serve.limits.queue_frames"),
                                       ({"allowed_origins": ["evil.example"]}, "serve.allowed_origins[0]"),
                                       ({"jpeg_quality": 0}, "serve.jpeg_quality"), ({"bogus": 1}, "serve.bogus"),
                                       # not a host at all (it was "reachable from other hosts")
                                       ({"host": "my host", "insecure": True}, "serve.host"),
                                       ({"host": "http://robot", "insecure": True}, "serve.host")])
def test_bad_values_name_their_key(block, key):
    with pytest.raises(ConfigError) as exc:
        _load(block)
    assert exc.value.path == key


def test_serve_flag():
    assert parse_serve_arg("8080") == (None, 8080)
    assert parse_serve_arg("0.0.0.0:8080") == ("0.0.0.0", 8080)
    assert parse_serve_arg("[::1]:9") == ("::1", 9)
    for bad in ("x", "1.2.3.4:", "99999"):
        with pytest.raises(ValueError):
            parse_serve_arg(bad)
    cfg = with_serve(load_config({"source": SRC}), "127.0.0.1:0")
    assert cfg.serve.port == 0
    with pytest.raises(ConfigError) as exc:
        with_serve(load_config({"source": SRC}), "0.0.0.0:8080")
    assert exc.value.path == "serve.insecure"


def test_token_and_origin_rules(tmp_path):
    tok = run_token(str(tmp_path), None)
    assert len(tok) >= 24 and run_token(str(tmp_path), None) == tok  # a restarted server keeps it
    assert (tmp_path / "serve-token").stat().st_mode & 0o077 == 0
    assert run_token(str(tmp_path), "configured-token-12345") == "configured-token-12345"
    assert check_token(tok, None, tok) is None and check_token(None, tok, tok) is None
    assert "required" in check_token(None, None, tok)
    assert "wrong token" in check_token("x" * 30, None, tok)
    assert check_origin("http://127.0.0.1:8000", "127.0.0.1:8000", "http", []) is None
    assert check_origin("http://localhost:8000", "127.0.0.1:8000", "http", []) is None
    assert check_origin(None, "127.0.0.1:8000", "http", []) is None
    assert "not allowed" in check_origin("http://evil.example", "127.0.0.1:8000", "http", [])
    assert "not allowed" in check_origin("http://127.0.0.1:9999", "127.0.0.1:8000", "http", [])
    assert "not allowed" in check_origin("https://127.0.0.1:8000", "127.0.0.1:8000", "http", [])
    assert check_origin("https://ops.example", "10.0.0.2:8000", "https", ["https://ops.example"]) is None


@pytest.mark.parametrize("bad", ["http://view.example.org", "view.example.org/path", "a b", "", "host:port"])
def test_allowed_hosts_are_checked_at_load(bad):
    with pytest.raises(ConfigError) as exc:
        _load({"allowed_hosts": ["ok.example.org", bad]})
    assert exc.value.path == "serve.allowed_hosts[1]" and "\n" not in str(exc.value)
    assert _load({"allowed_hosts": ["view.example.org", "view.example.org:443", "[::1]:8765"]}).serve.allowed_hosts


def test_the_host_rule():
    from pointflow.serve.auth import check_host

    for ok in ("127.0.0.1:8765", "localhost:8765", "[::1]:8765", "10.1.2.3", "proxy.lan:443"):
        assert check_host(ok, "127.0.0.1", ["proxy.lan"]) is None, ok
    for bad in ("evil.example:8765", "127.0.0.1.evil.example", "", None):
        assert check_host(bad, "127.0.0.1", ["proxy.lan"]) is not None, bad
