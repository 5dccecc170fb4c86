"""Stage-latency profile from collected spans + stage stats.

Per trace id (one chunk) the first end time of every event is taken. A stage's latency is
the time from the previous event the chunk passed (its end) to this event's end, so waiting
in a queue is charged to the stage that waited; the first event's latency is its own
duration. End to end = first start → ``frame_done`` end. Like Holoscan's data-flow tracking,
the first and last ``skip`` chunks (warm-up / cool-down) are left out of the statistics when
there are enough of them.

Outputs (:func:`write_profile`): ``profile.json``, ``trace.json`` (Chrome trace-event format,
opens in Perfetto / chrome://tracing) and ``latency.png``; :func:`format_table` prints the
table; :func:`live_summary` is the one-liner of ``pointflow run``.
"""
from __future__ import annotations

import json
import os
import re
from typing import Any, Optional

import numpy as np

from .collector import SpanCollector, SpanTable
from .spans import EVENTS

#: Chunks skipped at the start and at the end (warm-up / cool-down).
DEFAULT_SKIP = 10
#: trace.json keeps at most this many slices (the newest chunks' spans).
MAX_TRACE_SLICES = 300_000
_NONE = np.iinfo(np.int64).max


def _pcts(ms: np.ndarray) -> dict[str, Any]:
    if ms.size == 0:
        return {"count": 0, "p50": None, "p95": None, "p99": None, "max": None, "mean": None}
    p50, p95, p99 = np.percentile(ms, [50, 95, 99])
    return {"count": int(ms.size), "p50": round(float(p50), 4), "p95": round(float(p95), 4),
            "p99": round(float(p99), 4), "max": round(float(ms.max()), 4), "mean": round(float(ms.mean()), 4)}


class _Traces:
    """Per-trace matrices T0/T1[trace, event] (first start / end; _NONE = not seen)."""

    def __init__(self, t: SpanTable):
        self.ids, inv = np.unique(t.trace_id, return_inverse=True)
        ne = len(t.event_names)
        self.T0 = np.full((self.ids.size, ne), _NONE, np.int64)
        self.T1 = np.full((self.ids.size, ne), _NONE, np.int64)
        self.N = np.zeros((self.ids.size, ne), np.int64)
        np.minimum.at(self.T0, (inv, t.event), t.t0_ns)
        np.minimum.at(self.T1, (inv, t.event), t.t1_ns)
        np.maximum.at(self.N, (inv, t.event), t.n)
        self.inv = inv
        # canonical order first, unknown events after
        known = [t.event_names.index(e) for e in EVENTS if e in t.event_names]
        self.order = known + [i for i in range(ne) if i not in known]
        self.names = t.event_names
        self.start = self.T0.min(axis=1) if ne else np.zeros(0, np.int64)

    def kept(self, skip: int) -> tuple[np.ndarray, int]:
        """The chunks the statistics use (the table and latency.png alike): all but the first
        and last ``skip`` by start time, when there are more than ``4 * skip``."""
        keep = np.ones(self.ids.size, bool)
        if self.ids.size > 4 * skip and skip > 0:
            by_start = np.argsort(self.start, kind="stable")
            keep[by_start[:skip]] = False
            keep[by_start[-skip:]] = False
            return keep, 2 * skip
        return keep, 0

    def stage_latencies(self):
        """(event index, name, seen, latency ns) in pipeline order; latency = this event's end
        minus the end of the previous event the chunk passed (first event: its own duration)."""
        prev = np.full(self.ids.size, _NONE, np.int64)
        for j in self.order:
            seen = self.T1[:, j] != _NONE
            yield j, self.names[j], seen, np.where(prev != _NONE, self.T1[:, j] - prev, self.T1[:, j] - self.T0[:, j])
            prev = np.where(seen, self.T1[:, j], prev)


def build_profile(collector: SpanCollector | SpanTable | None, stats: Optional[dict] = None, *,
                  skip: int = DEFAULT_SKIP) -> dict[str, Any]:
    """Per-stage and end-to-end latency (count, p50/p95/p99/max ms), throughput, drops by
    reason and per-process CPU%/RSS (from ``stats``, the supervisor's ``stats()`` dict)."""
    stats = stats or {}
    if isinstance(collector, SpanCollector):
        table = collector.table()
        coll = collector.counters()
    elif isinstance(collector, SpanTable):
        table, coll = collector, {"received": len(collector)}
    else:
        table, coll = None, {"received": 0}
    out: dict[str, Any] = {"version": 1, "collector": coll, "stages": {}, "end_to_end": _pcts(np.zeros(0))}
    if table is not None and len(table):
        tr = _Traces(table)
        ntr = tr.ids.size
        keep, skipped = tr.kept(skip)
        t_lo, t_hi = int(table.t0_ns.min()), int(table.t1_ns.max())
        out["window"] = {"t0_ns": t_lo, "t1_ns": t_hi, "duration_s": round((t_hi - t_lo) / 1e9, 4)}
        out["traces"] = {"total": int(ntr), "skipped_warmup_cooldown": skipped, "kept": int(keep.sum())}
        for j, name, seen, lat in tr.stage_latencies():
            dur = tr.T1[:, j] - tr.T0[:, j]
            m = seen & keep
            ms = lat[m] / 1e6
            ends = tr.T1[m, j]
            span_s = (ends.max() - ends.min()) / 1e9 if ends.size > 1 else 0.0
            recorders = sorted({table.stage_names[s] for s in np.unique(table.stage[table.event == j])})
            out["stages"][name] = {
                **_pcts(ms),
                "duration": _pcts(dur[m] / 1e6),
                "chunks_per_s": round((ends.size - 1) / span_s, 3) if span_s > 0 else None,
                "points_per_s": round(float(tr.N[m, j].sum()) / span_s, 1) if span_s > 0 else None,
                "recorded_by": recorders,
            }
        if "frame_done" in tr.names:
            fd = tr.names.index("frame_done")
            m = (tr.T1[:, fd] != _NONE) & keep
            out["end_to_end"] = _pcts((tr.T1[m, fd] - tr.start[m]) / 1e6)
            out["traces"]["complete"] = int(m.sum())
            if "transport_receive" in tr.names:  # from the source's send (end of its span)
                tx = tr.names.index("transport_receive")
                m2 = m & (tr.T1[:, tx] != _NONE)
                out["send_to_frame"] = _pcts((tr.T1[m2, fd] - tr.T1[m2, tx]) / 1e6)
    out["processes"] = {}
    out["drops"] = {}
    for name, s in (stats.get("stages") or {}).items():
        out["processes"][name] = {k: s.get(k) for k in ("pid", "kind", "cpu_percent", "rss_bytes", "points_in",
                                                        "points_out", "restarts")}
        drops = {k: v for k, v in (s.get("drops") or {}).items() if v}
        if drops:
            out["drops"][name] = drops
    out["frames"] = stats.get("frames")
    out["elapsed_s"] = stats.get("elapsed_s")
    cad = (stats.get("stages") or {}).get("cadence") or {}
    if cad:
        out["cadence"] = {k: cad.get(k) for k in ("target_hz", "achieved_hz", "publish_hz", "jitter_ms", "skipped",
                                                  "interval_ms", "budget") if k in cad}
    mp = (stats.get("stages") or {}).get("map") or {}
    if mp:  # the map layer (docs/map.md): what the map stage holds, what the render stage draws
        out["map"] = {k: mp.get(k) for k in MAP_KEYS}
        out["map"]["points_drawn"] = ((stats.get("stages") or {}).get("render") or {}).get("map_points")
    return out


#: The map stage's stats the profile shows (docs/map.md).
MAP_KEYS = ("map_nodes", "map_points", "map_nodes_loaded", "map_cache_bytes", "map_cache_mb", "map_cache_hits",
            "map_cache_misses", "map_load_ms_p50", "map_load_ms_max", "map_open_s", "map_refine_ms", "map_error")


# --------------------------------------------------------------------------- trace.json
def chrome_trace(table: SpanTable, processes: Optional[dict[int, str]] = None,
                 max_slices: int = MAX_TRACE_SLICES) -> dict[str, Any]:
    """Chrome trace-event JSON: one ``X`` slice per span (µs), one track per process."""
    n = len(table)
    sel = np.arange(max(0, n - max_slices), n)
    base = int(table.t0_ns.min()) if n else 0
    events: list[dict[str, Any]] = []
    pids = {}
    for i, p in enumerate(np.unique(table.pid[sel]) if n else []):
        stage_idx = table.stage[sel][table.pid[sel] == p][0]
        pids[int(p)] = (processes or {}).get(int(p)) or table.stage_names[int(stage_idx)]
    order = {e: k for k, e in enumerate(EVENTS)}
    for p, stage in pids.items():
        events.append({"name": "process_name", "ph": "M", "pid": p, "tid": p, "args": {"name": f"{stage} ({p})"}})
        events.append({"name": "thread_name", "ph": "M", "pid": p, "tid": p, "args": {"name": stage}})
        first_ev = table.event_names[int(table.event[sel][table.pid[sel] == p][0])]
        events.append({"name": "process_sort_index", "ph": "M", "pid": p, "tid": p,
                       "args": {"sort_index": order.get(first_ev, len(order))}})
    ts = (table.t0_ns[sel] - base) / 1e3
    dur = np.maximum(table.t1_ns[sel] - table.t0_ns[sel], 0) / 1e3
    for k, i in enumerate(sel.tolist()):
        events.append({"name": table.event_names[int(table.event[i])], "cat": "pointflow", "ph": "X",
                       "ts": round(float(ts[k]), 3), "dur": round(float(dur[k]), 3),
                       "pid": int(table.pid[i]), "tid": int(table.pid[i]),
                       "args": {"trace_id": f"{int(table.trace_id[i]):016x}", "points": int(table.n[i])}})
    return {"traceEvents": events, "displayTimeUnit": "ms",
            "otherData": {"clock": "CLOCK_MONOTONIC", "base_ns": base, "slices": int(sel.size), "spans": n}}


# --------------------------------------------------------------------------- latency.png
def plot_latency(table: SpanTable, profile: dict[str, Any], path: str, *,
                 skip: int = DEFAULT_SKIP) -> dict[str, np.ndarray]:
    """Per-stage latency distributions (box: p50 + IQR, whiskers p1–p99) and a timeline, of
    the same chunks as the printed table (warm-up/cool-down left out alike); returns the
    plotted latencies (ms) by row."""
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(11, 8.5), dpi=100)
    trc = profile.get("traces") or {}
    fig.suptitle("pointflow stage latency" + (
        f" — {trc['kept']} chunks ({trc.get('skipped_warmup_cooldown', 0)} warm-up/cool-down left out, "
        f"{trc.get('complete', 0)} reached frame_done)" if trc else ""))
    data, labels, series = [], [], []
    if len(table):
        tr = _Traces(table)
        keep, _ = tr.kept(skip)
        for j, name, seen, lat_ns in tr.stage_latencies():
            m = seen & keep
            lat = lat_ns[m] / 1e6
            data.append(lat)
            labels.append(name)
            series.append(((tr.T1[m, j] - tr.start.min()) / 1e9, lat))
        if "frame_done" in tr.names:
            fd = tr.names.index("frame_done")
            m = (tr.T1[:, fd] != _NONE) & keep
            e2e = (tr.T1[m, fd] - tr.start[m]) / 1e6
            data.append(e2e)
            labels.append("end_to_end")
            series.append(((tr.T1[m, fd] - tr.start.min()) / 1e9, e2e))
        nonempty = [(d, l) for d, l in zip(data, labels) if d.size]
        if nonempty:
            try:
                ax1.boxplot([d for d, _ in nonempty], whis=(1, 99), showfliers=False, orientation="horizontal")
            except TypeError:  # matplotlib < 3.10
                ax1.boxplot([d for d, _ in nonempty], whis=(1, 99), showfliers=False, vert=False)
            ax1.set_yticks(range(1, len(nonempty) + 1), [l for _, l in nonempty])
            for k, (d, _) in enumerate(nonempty, start=1):
                p50, p99 = np.percentile(d, [50, 99])
                ax1.annotate(f"p50 {p50:.2f}  p99 {p99:.2f} ms", (p99, k), xytext=(6, 0),
                             textcoords="offset points", va="center", fontsize=8)
            ax1.set_xscale("symlog", linthresh=1.0)
            ax1.invert_yaxis()  # pipeline order top to bottom
            ax1.set_xlim(left=0)
        for (x, y), lab in zip(series, labels):
            if x.size:
                ax2.plot(x, y, ".", ms=3, label=lab, alpha=0.7)
        if any(x.size for x, _ in series):
            ax2.set_yscale("symlog", linthresh=1.0)
            ax2.set_ylim(bottom=0)
            ax2.legend(fontsize=8, loc="upper right", markerscale=3)
    else:
        ax1.text(0.5, 0.5, "no spans collected (tracing off or nothing flowed)", ha="center", va="center",
                 transform=ax1.transAxes)
    ax1.set_xlabel("latency (ms, time since the chunk's previous stage)")
    ax1.set_title("per-stage latency distribution (box p25–p75, whiskers p1–p99)")
    ax2.set_xlabel("time since first span (s)")
    ax2.set_ylabel("latency (ms)")
    ax2.set_title("timeline")
    ax1.grid(True, axis="x", alpha=0.3)
    ax2.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return dict(zip(labels, data))


# --------------------------------------------------------------------------- outputs
def write_profile(out_dir: str, collector: SpanCollector | SpanTable | None, stats: Optional[dict] = None, *,
                  skip: int = DEFAULT_SKIP) -> dict[str, Any]:
    """Write ``profile.json``, ``trace.json`` and ``latency.png`` into ``out_dir``; return the profile."""
    os.makedirs(out_dir, exist_ok=True)
    if isinstance(collector, SpanCollector):
        collector.poll(0)
        table = collector.table()
        procs = collector.processes
    elif isinstance(collector, SpanTable):
        table, procs = collector, {}
    else:
        table, procs = SpanCollector(None, None).table(), {}
    profile = build_profile(collector if collector is not None else table, stats, skip=skip)
    files = {k: os.path.join(out_dir, f) for k, f in
             (("profile", "profile.json"), ("trace", "trace.json"), ("plot", "latency.png"))}
    profile["files"] = files
    with open(files["trace"], "w") as f:
        json.dump(chrome_trace(table, procs), f, separators=(",", ":"))
    plot_latency(table, profile, files["plot"], skip=skip)
    with open(files["profile"], "w") as f:
        json.dump(profile, f, indent=1, default=_json_default)
    return profile


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    return str(o)


def _f(v, spec: str = ".2f") -> str:
    return "-" if v is None else format(v, spec)


def format_table(profile: dict[str, Any]) -> str:
    """A readable table of the profile (stages, end to end, processes, drops)."""
    lines = []
    tr = profile.get("traces") or {}
    lines.append(f"chunks traced: {tr.get('total', 0)} (warm-up/cool-down skipped: "
                 f"{tr.get('skipped_warmup_cooldown', 0)}, complete: {tr.get('complete', 0)})")
    hdr = f"{'stage':<18}{'count':>8}{'p50 ms':>10}{'p95 ms':>10}{'p99 ms':>10}{'max ms':>10}{'chunks/s':>10}{'Mpts/s':>9}"
    lines += [hdr, "-" * len(hdr)]
    rows = list((profile.get("stages") or {}).items()) + [("end_to_end", profile.get("end_to_end") or {})]
    if profile.get("send_to_frame"):
        rows.append(("send_to_frame", profile["send_to_frame"]))
    for name, s in rows:
        pps = s.get("points_per_s")
        lines.append(f"{name:<18}{s.get('count', 0):>8}{_f(s.get('p50')):>10}{_f(s.get('p95')):>10}"
                     f"{_f(s.get('p99')):>10}{_f(s.get('max')):>10}{_f(s.get('chunks_per_s'), '.1f'):>10}"
                     f"{_f(None if not pps else pps / 1e6, '.2f'):>9}")
    procs = profile.get("processes") or {}
    if procs:
        lines.append("")
        h2 = f"{'process':<18}{'pid':>8}{'cpu %':>8}{'rss MB':>9}{'points in':>13}{'points out':>13}{'restarts':>9}"
        lines += [h2, "-" * len(h2)]
        for name, p in procs.items():
            rss = p.get("rss_bytes")
            lines.append(f"{name:<18}{p.get('pid') or '-':>8}{_f(p.get('cpu_percent'), '.1f'):>8}"
                         f"{_f(None if rss is None else rss / 2**20, '.1f'):>9}{p.get('points_in') or 0:>13,}"
                         f"{p.get('points_out') or 0:>13,}{p.get('restarts') or 0:>9}")
    drops = profile.get("drops") or {}
    lines.append("")
    if drops:
        lines.append("drops: " + "; ".join(f"{st}: " + ", ".join(f"{r}={n:,}" for r, n in d.items())
                                           for st, d in drops.items()))
    else:
        lines.append("drops: none")
    cad = profile.get("cadence")
    if cad:
        j = cad.get("jitter_ms") or {}
        lines.append(f"cadence: target {_f(cad.get('target_hz'), '.1f')} Hz, achieved {_f(cad.get('achieved_hz'), '.2f')} Hz, "
                     f"published {_f(cad.get('publish_hz'), '.2f')} Hz, jitter p50 {_f(j.get('p50'), '.3f')} / "
                     f"p99 {_f(j.get('p99'), '.3f')} / max {_f(j.get('max'), '.3f')} ms, skipped {cad.get('skipped') or {}}")
    mp = profile.get("map")
    if mp:
        lines.append(f"map: {mp.get('map_nodes') or 0} nodes, {mp.get('points_drawn') or 0:,} points drawn, "
                     f"{mp.get('map_nodes_loaded') or 0} node loads (load p50 {_f(mp.get('map_load_ms_p50'))} / "
                     f"max {_f(mp.get('map_load_ms_max'))} ms), cache {_f((mp.get('map_cache_bytes') or 0) / 2**20, '.1f')}"
                     f" of {_f(mp.get('map_cache_mb'), '.0f')} MB" + (f", error: {mp['map_error']}" if mp.get("map_error") else ""))
    coll = profile.get("collector") or {}
    if coll.get("dropped") or coll.get("bad_batches"):
        lines.append(f"span collector: {coll.get('dropped', 0)} spans over the memory cap, "
                     f"{coll.get('bad_batches', 0)} bad batches")
    return "\n".join(lines)


def _n(n: float) -> str:
    for unit, div in (("G", 1e9), ("M", 1e6), ("k", 1e3)):
        if abs(n) >= div:
            return f"{n / div:.1f}{unit}"
    return f"{n:.0f}"


def live_summary(stats: dict) -> str:
    """One line for ``pointflow run``: input, ring fill, frames, cadence, drops, evictions, a
    file source's progress, CPU."""
    st = stats.get("stages") or {}
    src_out = sum(s.get("points_out", 0) or 0 for s in st.values() if s.get("kind") == "source")
    drops = sum(sum((s.get("drops") or {}).values()) for s in st.values())
    ring = stats.get("ring") or {}
    cad = st.get("cadence") or {}
    ren = st.get("render") or {}
    parts = [f"t={stats.get('elapsed_s', 0) or 0:6.1f}s", f"in={_n(src_out)}",
             f"ring={_n(ring.get('total_points', 0) or 0)}/{_n(ring.get('capacity', 0) or 0)}",
             f"frames={stats.get('frames', 0) or 0}"]
    fms = ren.get("frame_ms_ema") or ren.get("frame_ms")
    if fms:
        parts.append(f"frame={fms:.1f}ms")
    if cad:
        j = (cad.get("jitter_ms") or {}).get("p99")
        skipped = sum((cad.get("skipped") or {}).values())
        parts.append(f"cadence={cad.get('achieved_hz', 0) or 0:.1f}Hz"
                     + (f" p99jit={j:.2f}ms" if j is not None else "") + (f" skip={skipped}" if skipped else ""))
    mp = st.get("map") or {}
    if mp:
        if mp.get("map_error"):
            parts.append("map=error")
        elif mp.get("map_index_pct") is not None:  # a first open builds its index (a preview may be drawn)
            parts.append(f"map: indexing {mp['map_index_pct']}%"
                         + (f" map={_n(ren['map_points'])}" if ren.get("map_points") else ""))
        else:
            parts.append(f"map={_n(ren.get('map_points', 0) or 0)}")
    parts.append(f"drops={_n(drops)}")
    # points the ring pushed out to make room (a file bigger than the ring loses its start here)
    parts.append(f"evicted={_n(sum(s.get('ring_evicted', 0) or 0 for s in st.values()))}")
    for name, s in st.items():  # a replay's share sent (its own bar would fight this line)
        if s.get("kind") == "source" and s.get("transport_progress") is not None:
            parts.append(f"{name}={min(1.0, s['transport_progress']) * 100:.0f}%"
                         + (f" of {_n(s['transport_total'])}" if s.get("transport_total") else ""))
    acc = stats.get("accounting") or {}
    refused = sum(s.get("transport_refused_handshakes", 0) or 0 for s in st.values())
    if "lost_in_transit" in acc:  # a link from `pointflow send` (docs/remote.md)
        parts.append(f"link_lost={_n(acc['lost_in_transit'])}" + (f" refused={refused}" if refused else ""))
    elif refused:  # nothing came over the link: a refused handshake is the likely reason
        parts.append(f"link refused={refused}")
    rec = st.get("recorder")
    if rec:  # the recording (docs/record.md): bytes written, what it missed, a stop
        missed = (acc.get("record_dropped", 0) or 0) + (acc.get("recorder_dropped", 0) or 0)
        parts.append(f"rec={(rec.get('record_bytes', 0) or 0) / 1e6:.1f}MB/{rec.get('record_messages', 0) or 0}msg"
                     + (f" missed={_n(missed)}" if missed else "")
                     + (f" STOPPED:{rec['record_error']}" if rec.get("record_error") else ""))
    cpu = " ".join(f"{n[:3]}:{s.get('cpu_percent', 0) or 0:.0f}%" for n, s in st.items())
    if cpu:
        parts.append(f"cpu[{cpu}]")
    if stats.get("failure"):  # the supervisor printed the error itself, once (issue 31.5)
        m = re.match(r"stage (\S+?):? ", stats["failure"])
        parts.append(f"FAILED ({'stage ' + m.group(1) + ': ' if m else ''}the error is above)")
    return "  ".join(parts)
