"""Profile numbers, Chrome trace.json (validated against the trace-event format), latency.png."""
import json
import struct

import numpy as np
import pytest

from pointflow.profiling.collector import SpanCollector
from pointflow.profiling.report import build_profile, chrome_trace, format_table, live_summary, write_profile
from pointflow.profiling.spans import EVENTS

MS = 1_000_000
PIDS = {"source": 101, "ingest": 102, "cadence": 103, "render": 104}
STAGE_OF = {"transport_receive": "source", "transform": "ingest", "ingest_packed": "ingest", "ring_committed": "ingest",
            "cadence_snapshot": "cadence", "render_upload": "render", "frame_done": "render"}


def synthetic(n=100, drop_last_frame=False):
    """Trace k starts at k*50 ms; stage j of trace k takes (j+1) + (k % 5) ms, its span
    lasts 0.5 ms at the end of that. Returns the collector and the expected latency matrix."""
    coll = SpanCollector(None, None)
    lat = np.zeros((n, len(EVENTS)))
    batches = {s: [] for s in PIDS}
    for k in range(n):
        t = 10**12 + k * 50 * MS
        start = t
        for j, ev in enumerate(EVENTS):
            if drop_last_frame and k == n - 1 and ev == "frame_done":
                continue
            d = (j + 1 + k % 5) * MS
            if j == 0:
                t0, t1 = t, t + d
            else:
                t0, t1 = t + d - MS // 2, t + d
            lat[k, j] = d / MS
            t = t1
            batches[STAGE_OF[ev]].append([k + 1, ev, t0, t1, 1000])
    for s, spans in batches.items():
        coll.add_batch(json.dumps({"stage": s, "pid": PIDS[s], "spans": spans}).encode())
    return coll, lat


STATS = {
    "stages": {
        "source": {"pid": 101, "kind": "source", "cpu_percent": 12.5, "rss_bytes": 80 << 20, "points_in": 0,
                   "points_out": 100_000, "drops": {}},
        "ingest": {"pid": 102, "kind": "ingest", "cpu_percent": 30.0, "rss_bytes": 90 << 20, "points_in": 100_000,
                   "points_out": 99_000, "drops": {"bad_count": 2, "ring_overwrite": 1000, "zero": 0}},
        "cadence": {"pid": 103, "kind": "cadence", "cpu_percent": 3.0, "rss_bytes": 60 << 20, "drops": {},
                    "target_hz": 60.0, "achieved_hz": 59.99, "publish_hz": 59.5,
                    "jitter_ms": {"p50": 0.1, "p99": 0.4, "max": 1.2}, "skipped": {"late": 2}},
        "render": {"pid": 104, "kind": "render", "cpu_percent": 80.0, "rss_bytes": 300 << 20, "drops": {},
                   "frames": 600, "frame_ms_ema": 9.5},
    },
    "frames": 600, "elapsed_s": 10.0, "ring": {"total_points": 50_000, "capacity": 100_000},
}


def test_stage_and_end_to_end_percentiles():
    coll, lat = synthetic(100)
    prof = build_profile(coll, STATS, skip=10)
    keep = slice(10, 90)  # starts are increasing in k: first/last 10 are warm-up/cool-down
    assert prof["traces"] == {"total": 100, "skipped_warmup_cooldown": 20, "kept": 80, "complete": 80}
    for j, ev in enumerate(EVENTS):
        s = prof["stages"][ev]
        exp = lat[keep, j]
        assert s["count"] == 80
        for q in (50, 95, 99):
            assert s[f"p{q}"] == pytest.approx(np.percentile(exp, q), abs=1e-3)
        assert s["max"] == pytest.approx(exp.max())
        assert s["recorded_by"] == [STAGE_OF[ev]]
        assert s["chunks_per_s"] == pytest.approx(20.0, rel=0.01)    # one chunk per 50 ms
        assert s["points_per_s"] == pytest.approx(20_000.0, rel=0.02)
        want_dur = 1.0 + np.arange(10, 90) % 5 if j == 0 else np.full(80, 0.5)
        assert s["duration"]["max"] == pytest.approx(want_dur.max())
    e2e = lat[keep].sum(axis=1)
    assert prof["end_to_end"]["p50"] == pytest.approx(np.percentile(e2e, 50), abs=1e-3)
    assert prof["end_to_end"]["p99"] == pytest.approx(np.percentile(e2e, 99), abs=1e-3)
    s2f = lat[keep, 1:].sum(axis=1)  # from the end of transport_receive (the send)
    assert prof["send_to_frame"]["p50"] == pytest.approx(np.percentile(s2f, 50), abs=1e-3)
    assert prof["drops"] == {"ingest": {"bad_count": 2, "ring_overwrite": 1000}}
    assert prof["processes"]["render"]["cpu_percent"] == 80.0
    assert prof["processes"]["cadence"]["rss_bytes"] == 60 << 20
    assert prof["cadence"]["achieved_hz"] == 59.99


def test_incomplete_traces_and_no_skip_when_few():
    coll, lat = synthetic(12, drop_last_frame=True)
    prof = build_profile(coll, {}, skip=10)
    assert prof["traces"]["skipped_warmup_cooldown"] == 0      # too few chunks to skip any
    assert prof["stages"]["frame_done"]["count"] == 11
    assert prof["end_to_end"]["count"] == 11
    assert prof["stages"]["render_upload"]["count"] == 12


def test_empty_profile():
    prof = build_profile(SpanCollector(None, None), {})
    assert prof["end_to_end"]["count"] == 0 and prof["stages"] == {}
    assert "end_to_end" in format_table(prof)


# --------------------------------------------------------------------------- trace.json
_META = {"process_name", "process_labels", "process_sort_index", "thread_name", "thread_sort_index"}


def validate_trace_events(doc) -> int:
    """Checks the Chrome Trace Event Format (JSON object form); returns the number of X slices."""
    assert isinstance(doc, dict) and isinstance(doc.get("traceEvents"), list)
    if "displayTimeUnit" in doc:
        assert doc["displayTimeUnit"] in ("ms", "ns")
    named: dict[int, str] = {}
    slices = 0
    for i, e in enumerate(doc["traceEvents"]):
        where = f"traceEvents[{i}]"
        assert isinstance(e, dict), where
        assert isinstance(e.get("ph"), str) and len(e["ph"]) == 1, where
        assert isinstance(e.get("name"), str) and e["name"], where
        for k in ("pid", "tid"):
            assert isinstance(e.get(k), int) and not isinstance(e[k], bool), f"{where}.{k}"
        if "args" in e:
            assert isinstance(e["args"], dict), where
        if e["ph"] == "M":
            assert e["name"] in _META, where
            if e["name"] in ("process_name", "thread_name"):
                assert isinstance(e["args"].get("name"), str), where
                if e["name"] == "process_name":
                    named[e["pid"]] = e["args"]["name"]
            continue
        assert isinstance(e.get("ts"), (int, float)) and e["ts"] >= 0, f"{where}.ts"
        if "cat" in e:
            assert isinstance(e["cat"], str), where
        if e["ph"] == "X":
            assert isinstance(e.get("dur"), (int, float)) and e["dur"] >= 0, f"{where}.dur"
            assert e["pid"] in named, f"{where}: process {e['pid']} has no process_name"
            slices += 1
        else:
            assert e["ph"] in "BEiIbenCsftPONDc", f"{where}: unknown phase {e['ph']!r}"
    json.dumps(doc)  # serialisable
    return slices


def test_trace_json_is_valid_one_track_per_process_one_slice_per_chunk_stage(tmp_path):
    coll, lat = synthetic(30)
    doc = chrome_trace(coll.table(), coll.processes)
    assert validate_trace_events(doc) == 30 * len(EVENTS)
    names = {e["pid"]: e["args"]["name"] for e in doc["traceEvents"] if e.get("name") == "process_name"}
    assert set(names) == set(PIDS.values()) and names[104].startswith("render")
    x = [e for e in doc["traceEvents"] if e["ph"] == "X"]
    assert {(e["args"]["trace_id"], e["name"]) for e in x} == {(f"{k:016x}", ev) for k in range(1, 31) for ev in EVENTS}
    assert all(e["pid"] == PIDS[STAGE_OF[e["name"]]] == e["tid"] for e in x)
    # µs: transport_receive of trace 2 starts 50 ms after trace 1's
    tr = {e["args"]["trace_id"]: e for e in x if e["name"] == "transport_receive"}
    assert tr[f"{2:016x}"]["ts"] - tr[f"{1:016x}"]["ts"] == pytest.approx(50_000)
    assert tr[f"{2:016x}"]["dur"] == pytest.approx(lat[1, 0] * 1000)


def test_validator_rejects_bad_trace():
    with pytest.raises(AssertionError):
        validate_trace_events({"traceEvents": [{"ph": "X", "name": "a", "pid": 1, "tid": 1, "ts": 0}]})
    with pytest.raises(AssertionError):
        validate_trace_events({"traceEvents": [{"ph": "X", "name": "a", "pid": 1, "tid": 1, "ts": 0, "dur": 1}]})


def test_write_profile_files(tmp_path):
    coll, _ = synthetic(60)
    prof = write_profile(str(tmp_path), coll, STATS)
    on_disk = json.loads((tmp_path / "profile.json").read_text())
    assert on_disk["stages"]["frame_done"]["count"] == prof["stages"]["frame_done"]["count"] == 40
    assert validate_trace_events(json.loads((tmp_path / "trace.json").read_text())) == 60 * len(EVENTS)
    png = (tmp_path / "latency.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    w, h = struct.unpack(">II", png[16:24])
    assert (w, h) == (1100, 850)
    from PIL import Image

    img = np.asarray(Image.open(tmp_path / "latency.png").convert("L"))
    assert img.std() > 10  # drawn, not blank
    write_profile(str(tmp_path / "empty"), None, {})       # no spans: still three files
    assert {p.name for p in (tmp_path / "empty").iterdir()} == {"profile.json", "trace.json", "latency.png"}


def test_format_table_and_live_summary():
    coll, _ = synthetic(60)
    text = format_table(build_profile(coll, STATS))
    lines = text.splitlines()
    for ev in EVENTS + ("end_to_end",):
        assert any(line.startswith(ev) for line in lines), ev
    assert "bad_count=2" in text and "ring_overwrite=1,000" in text
    assert any(line.startswith("render") and "80.0" in line and "300.0" in line for line in lines)
    assert "achieved 59.99 Hz" in text
    s = live_summary(STATS)
    assert "\n" not in s
    for part in ("t=  10.0s", "in=100.0k", "ring=50.0k/100.0k", "frames=600", "frame=9.5ms",
                 "cadence=60.0Hz", "p99jit=0.40ms", "skip=2", "drops=1.0k", "ren:80%"):
        assert part in s, (part, s)


def test_latency_png_plots_the_chunks_the_table_counts(tmp_path):
    """One chunk set for the chart and the table (issue 22, item 6): warm-up chunks with huge
    latencies are left out of both, so counts and p99 agree row by row."""
    from pointflow.profiling.report import plot_latency

    coll, _ = synthetic(100, drop_last_frame=True)
    table = coll.table()
    slow = table.trace_id <= 3  # the first chunks (warm-up) 10 s late at ingest
    table.t1_ns[slow & (np.array(table.event_names)[table.event] != "transport_receive")] += 10_000 * MS
    prof = build_profile(table, STATS, skip=10)
    plotted = plot_latency(table, prof, str(tmp_path / "latency.png"), skip=10)
    assert (tmp_path / "latency.png").stat().st_size > 0
    for name, st in prof["stages"].items():
        assert plotted[name].size == st["count"], name
        assert np.percentile(plotted[name], 99) == pytest.approx(st["p99"], abs=1e-3), name
        assert plotted[name].max() < 1000  # the late warm-up chunks are not in the chart
    assert plotted["end_to_end"].size == prof["end_to_end"]["count"] == prof["traces"]["complete"]
