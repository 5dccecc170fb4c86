"""A stage spinning in a call that holds the GIL is hung, though it uses the CPU (issue 19).

Its pulse thread cannot talk, and to the kernel it looks like a starved stage, so it used to
be kept until ``stall_after_ms`` (30 s). The supervisor now watches its main thread: never
asleep, and on the CPU for ``supervisor.stuck_cpu_ms`` of the silence (liveness.py).

The spin is real: a plugin source whose first incarnation runs a regular expression with
catastrophic backtracking (CPython's ``re`` holds the GIL in C for the whole match). The
restarted source finds its marker file and streams normally."""
from __future__ import annotations

import textwrap

from pointflow import Pipeline

from ..helpers import assert_gone, assert_segments_gone, small_config, wait_for

PLUGIN = textwrap.dedent('''
    import dataclasses, os, re, time
    import numpy as np
    from pointflow.chunk import PointChunk
    from pointflow.ingest.transports import Transport

    @dataclasses.dataclass
    class SpinOptions:
        marker: str = ""

    class SpinTransport(Transport):
        name = "gil_spin"
        options_schema = SpinOptions

        def chunks(self):
            k = 0
            while True:
                pos = np.random.default_rng(k).random((1000, 3))
                yield PointChunk(positions=pos, channels={}, source_id=self.source_id)
                k += 1
                if k == 20 and not os.path.exists(self.opts.marker):
                    open(self.opts.marker, "w").close()
                    # exponential backtracking: runs for ages in C, holding the GIL
                    re.match(r"(a+)+$", "a" * 64 + "b")
                time.sleep(0.02)
''')


def test_a_stage_spinning_while_holding_the_gil_is_replaced(tmp_path, monkeypatch):
    (tmp_path / "gil_spin_plugin.py").write_text(PLUGIN)
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    monkeypatch.syspath_prepend(str(tmp_path))
    marker = tmp_path / "spun"
    cfg = small_config(source={"transport": "gil_spin_plugin:SpinTransport", "options": {"marker": str(marker)}},
                       # a stall past stall_after_ms would also replace it: far beyond this test
                       supervisor={"max_restarts": 3, "stall_after_ms": 600_000, "stuck_cpu_ms": 1000})
    with Pipeline.from_dict(cfg, out_dir=str(tmp_path)) as pipe:
        assert wait_for(lambda: marker.exists(), 60), "the source never reached its spin"
        first = pipe.stats()["stages"]["source"]["pid"]
        assert wait_for(lambda: pipe.stats()["stages"]["source"]["pid"] != first, 120), \
            f"a source spinning in C with the GIL held was not replaced: {pipe.stats()['events']}"
        events = pipe.stats()["events"]
        assert [(e["stage"], e["pid"]) for e in events] == [("source", first)], events
        assert "holds the GIL" in events[0]["reason"] and events[0]["reason"].startswith("hung"), events
        # the new incarnation streams: points keep arriving at ingest
        got = pipe.stats()["stages"]["ingest"]["points_in"]
        assert wait_for(lambda: pipe.stats()["stages"]["ingest"]["points_in"] >= got + 20_000, 60)
        pids = [v["pid"] for v in pipe.stats()["stages"].values()] + [first]
    assert_segments_gone(pipe.stats())
    assert_gone(pids)
