"""pointflow.connect over loopback with CURVE keys: every point arrives and is accounted on
both ends; a key the receiver does not accept is refused with the message `pointflow send`
gives for it (issue 28, item 2)."""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pointflow import Pipeline
from pointflow.remote.keys import create_keypair
from pointflow.testing import free_port as _free_port

from .helpers import REPO, api_config, known_clouds, run_script


@pytest.fixture
def keys(tmp_path):
    d = tmp_path / "keys"
    k = {n: tuple(map(str, create_keypair(n, d / n))) for n in ("viewer", "sensor", "intruder")}
    auth = tmp_path / "authorized"
    auth.mkdir()
    (auth / "sensor.key").write_text(Path(k["sensor"][0]).read_text())
    return k, str(auth)


def _receiver(port, keys):
    k, auth = keys
    cfg = api_config(sources=[{"transport": "zmq", "name": "link", "options": {
        "endpoint": f"tcp://127.0.0.1:{port}", "socket": "pull", "bind": True,
        "curve_secret_key": k["viewer"][1], "curve_authorized_keys": auth}}])
    p = Pipeline.from_dict(cfg, out_dir="")
    p.start()
    return p


def test_connect_sends_over_curve_and_both_ends_account(tmp_path, keys):
    k, _ = keys
    port = _free_port()
    recv = _receiver(port, keys)
    try:
        run_script(tmp_path, f"""
import json
import pointflow
from tests.api.helpers import known_clouds
link = pointflow.connect("tcp://127.0.0.1:{port}", socket="push", bind=False, source="sim",
                         curve_secret_key={k["sensor"][1]!r}, curve_server_key={k["viewer"][0]!r})
for pos, inten, rgb in known_clouds(20, 1000):
    link.send(pos, intensity=inten, rgb=rgb, frame="map")
stats = link.close()
json.dump(stats, open("send.json", "w"), default=str)
""")
        snd = json.loads((tmp_path / "send.json").read_text())
        end = time.monotonic() + 60
        while time.monotonic() < end and recv.stats()["accounting"]["ingest_written"] < 20_000:
            time.sleep(0.05)
        snap = recv.supervisor.ring.snapshot()
    finally:
        rcv = recv.stop()
    acc = snd["accounting"]
    assert acc["sources_received"] == acc["sender_received"] == acc["link_sent"] == 20_000 and acc["sender_balanced"]
    assert snd["stages"]["sim"]["points_out"] == 20_000
    ra = rcv["accounting"]
    assert ra["link_sent"] == ra["link_received"] == ra["ingest_written"] == 20_000 and ra["lost_in_transit"] == 0
    assert ra["lost_in_transit_by_source"] == {"sim": 0}
    assert rcv["stages"]["link"]["transport_handshakes"] >= 1
    want = np.concatenate([c[1] for c in known_clouds(20, 1000)])
    np.testing.assert_array_equal(np.sort(snap.channels["intensity"]), np.sort(want))


REFUSAL = re.compile(r"the server at \S+ refused this end's CURVE handshake \(status \d+; \d+ refused so far\): .*")


def _normalise(line: str) -> str:
    return re.sub(r"\(status \d+; \d+ refused so far\)", "(status N; K refused so far)", line)


def test_a_wrong_key_is_refused_with_the_same_message_as_pointflow_send(tmp_path, keys):
    k, _ = keys
    port = _free_port()
    recv = _receiver(port, keys)
    try:
        p = run_script(tmp_path, f"""
import time
import numpy as np
import pointflow
link = pointflow.connect("tcp://127.0.0.1:{port}", socket="push", bind=False,
                         curve_secret_key={k["intruder"][1]!r}, curve_server_key={k["viewer"][0]!r})
end = time.monotonic() + 60
try:
    while time.monotonic() < end:
        link.send(np.zeros((10, 3), np.float32))
        time.sleep(0.05)
    raise SystemExit("not refused within 60 s")
except pointflow.LinkRefused as exc:
    print("REFUSED:", exc)
finally:
    link.close()
""")
        refused = [l for l in p.stdout.splitlines() if l.startswith("REFUSED: ")]
        assert refused and REFUSAL.fullmatch(refused[0][len("REFUSED: "):]), p.stdout
        logged = [m.group(0) for m in map(REFUSAL.search, p.stderr.splitlines()) if m]
        assert logged, p.stderr  # the sender stage logs it too, as in `pointflow send`
        # `pointflow send` with the same link options and the same key
        cfg = {"source": {"transport": "synthetic", "name": "lidar",
                          "options": {"scan_hz": 10, "points_per_scan": 1000}},
               "send": {"endpoint": f"tcp://127.0.0.1:{port}", "socket": "push", "bind": False,
                        "curve_secret_key": k["intruder"][1], "curve_server_key": k["viewer"][0]}}
        (tmp_path / "send.yaml").write_text(json.dumps(cfg))
        exe = Path(sys.executable).with_name("pointflow")
        cli = [str(exe)] if exe.exists() else [sys.executable, "-m", "pointflow.cli"]
        env = dict(os.environ, PYTHONPATH=str(REPO))
        q = subprocess.run(cli + ["send", str(tmp_path / "send.yaml"), "--duration", "4", "--out", str(tmp_path / "o")],
                           capture_output=True, text=True, timeout=120, env=env, stdin=subprocess.DEVNULL)
        from_cli = [m.group(0) for m in map(REFUSAL.search, (q.stdout + q.stderr).splitlines()) if m]
        assert from_cli, q.stdout + q.stderr
        assert _normalise(from_cli[0]) == _normalise(refused[0][len("REFUSED: "):]) == _normalise(logged[0])
        st = recv.stats()
        assert st["stages"]["link"]["transport_refused_handshakes"] >= 2 and st["accounting"]["ingest_received"] == 0
        assert "failure" not in st and st["stages"]["link"]["restarts"] == 0
    finally:
        recv.stop()


def test_connect_over_zenoh(tmp_path):
    """The other engine: connect(engine="zenoh") publishes on <key>/<source>; a zenoh source
    subscribes; every point arrives and the link balances."""
    pytest.importorskip("zenoh", reason="eclipse-zenoh comes with the remote extra")
    port = _free_port()
    cfg = api_config(sources=[{"transport": "zenoh", "name": "link", "options": {
        "key": "pfapi/**", "zenoh": {"listen": [f"tcp/127.0.0.1:{port}"]}}}])
    recv = Pipeline.from_dict(cfg, out_dir="")
    recv.start()
    try:
        run_script(tmp_path, f"""
import json
import pointflow
from tests.api.helpers import known_clouds
with pointflow.connect("tcp/127.0.0.1:{port}", engine="zenoh", key="pfapi", source="sim",
                       wait_subscribers=1, wait_s=60) as link:
    for pos, inten, rgb in known_clouds(10, 1000):
        link.send(pos, intensity=inten, rgb=rgb)
""")
        end = time.monotonic() + 60
        while time.monotonic() < end and recv.stats()["accounting"]["ingest_written"] < 10_000:
            time.sleep(0.05)
    finally:
        rcv = recv.stop()
    ra = rcv["accounting"]
    assert ra["ingest_written"] == ra["link_received"] == ra["link_sent"] == 10_000 and ra["link_balanced"]
