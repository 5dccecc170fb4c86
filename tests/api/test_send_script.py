"""Pipeline.send from a plain script (no main guard): the ring holds exactly what was sent,
and stats() accounts for it; several threads at once (issue 28, item 1)."""
from __future__ import annotations

import json

import numpy as np

from .helpers import api_config, known_clouds, read_json, run_script

PRELUDE = """
import json, threading, time
import numpy as np
from pointflow import Pipeline
from tests.api.helpers import known_clouds

def settle(p, total):
    # until ingest took every point sent (generous: a busy machine)
    end = time.monotonic() + 120
    while time.monotonic() < end and p.stats()["accounting"]["ingest_written"] < total:
        p.wait(0.05)

def dump(p, path):
    snap = p.supervisor.ring.snapshot()
    np.savez(path, positions=snap.positions, **snap.channels)
"""


def _sorted(pos, inten, rgb):
    order = np.lexsort((pos[:, 2], pos[:, 1], pos[:, 0]))
    return pos[order], inten[order], rgb[order]


def _expected(clouds):
    pos = np.concatenate([c[0] for c in clouds]).astype(np.float64)
    return _sorted(pos, np.concatenate([c[1] for c in clouds]), np.concatenate([c[2] for c in clouds]))


def test_script_without_main_guard_sends_50_clouds(tmp_path):
    cfg = api_config(frames={"fixed": "map"})
    run_script(tmp_path, PRELUDE + f"""
cfg = json.loads({json.dumps(json.dumps(cfg))})
p = Pipeline.from_dict(cfg, out_dir="out")
p.start()
clouds = known_clouds(50, 1000)
for pos, inten, rgb in clouds:
    assert p.send(pos, frame="map", stamp_ns=1_700_000_000_000_000_000, intensity=inten, rgb=rgb) == len(pos)
settle(p, 50_000)
dump(p, "ring.npz")
json.dump(p.stats(), open("live.json", "w"), default=str)
p.stop()
""")
    ring = np.load(tmp_path / "ring.npz")
    got = _sorted(ring["positions"], ring["intensity"], ring["rgb"])
    want = _expected(known_clouds(50, 1000))
    assert len(got[0]) == 50_000
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)
    for stats in (read_json(tmp_path / "live.json"), read_json(tmp_path / "out" / "stats.json")):
        api = stats["stages"]["api"]
        assert api["kind"] == "source" and api["points_in"] == api["points_out"] == 50_000
        assert api["chunks_sent"] == 50 and api["drops"] == {} and api["rejected"] == {}
        acc = stats["accounting"]
        assert acc["sources_received"] == acc["sources_forwarded"] == 50_000 and acc["sources_balanced"]
        assert acc["ingest_received"] == acc["ingest_written"] == acc["ring_written"] == 50_000
        assert acc["lost_before_ingest"] == 0



def test_send_transforms_places_clouds_in_the_fixed_frame(tmp_path):
    cfg = api_config(frames={"fixed": "map"})
    run_script(tmp_path, PRELUDE + f"""
cfg = json.loads({json.dumps(json.dumps(cfg))})
p = Pipeline.from_dict(cfg, out_dir="out")
p.start()
assert p.send_transforms([{{"parent": "map", "child": "lidar", "stamp_ns": 0, "translation": [100.0, -20.0, 3.0],
                            "rotation": [0.0, 0.0, 0.0, 1.0], "static": True}}]) == 1
clouds = known_clouds(5, 1000)
for pos, inten, rgb in clouds:
    p.send(pos, frame="lidar", intensity=inten, rgb=rgb)
settle(p, 5000)
dump(p, "ring.npz")
p.stop()
""")
    ring = np.load(tmp_path / "ring.npz")
    got = _sorted(ring["positions"], ring["intensity"], ring["rgb"])
    want = list(_expected(known_clouds(5, 1000)))
    want[0] = want[0] + [100.0, -20.0, 3.0]
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)
    stats = read_json(tmp_path / "out" / "stats.json")
    assert stats["stages"]["api"]["transforms_sent"] == 1


def test_two_threads_and_a_source_added_while_running(tmp_path):
    run_script(tmp_path, PRELUDE + f"""
cfg = json.loads({json.dumps(json.dumps(api_config()))})
p = Pipeline.from_dict(cfg, out_dir="out")
p.start()
clouds = known_clouds(60, 500)
errors = []
def worker(part, source):
    try:
        for pos, inten, rgb in part:
            p.send(pos, source=source, intensity=inten, rgb=rgb)
    except Exception as exc:
        errors.append(repr(exc))
threads = [threading.Thread(target=worker, args=(clouds[0:20], "api")),
           threading.Thread(target=worker, args=(clouds[20:40], "api")),
           threading.Thread(target=worker, args=(clouds[40:60], "cam"))]  # "cam": added on first send
for t in threads: t.start()
for t in threads: t.join()
assert not errors, errors
settle(p, 30_000)
dump(p, "ring.npz")
p.stop()
""")
    ring = np.load(tmp_path / "ring.npz")
    got = _sorted(ring["positions"], ring["intensity"], ring["rgb"])
    for g, w in zip(got, _expected(known_clouds(60, 500))):
        np.testing.assert_array_equal(g, w)
    stats = read_json(tmp_path / "out" / "stats.json")
    assert stats["stages"]["api"]["points_out"] == 20_000 and stats["stages"]["api"]["chunks_sent"] == 40
    assert stats["stages"]["cam"]["points_out"] == 10_000 and stats["stages"]["cam"]["kind"] == "source"
    acc = stats["accounting"]
    assert acc["sources_forwarded"] == acc["ingest_written"] == 30_000 and acc["lost_before_ingest"] == 0
