"""``start(wait=False)``: back once the stages are spawned (issue 36, item 5); ``send`` works
at once, its clouds wait in ingest's socket until ingest is up, and ``starting`` turns false
once every stage has reported in."""
from __future__ import annotations

import numpy as np
import pytest

from pointflow import Pipeline

from .helpers import api_config


@pytest.mark.timeout(300)
def test_send_right_after_a_start_that_does_not_wait():
    xyz = np.random.default_rng(2).normal(size=(5000, 3)).astype(np.float32)
    p = Pipeline.from_dict(api_config())
    assert p.stages() == ["render", "cadence", "ingest", "api"]  # what it will start, before it does
    with pytest.raises(RuntimeError, match=r"pipeline has not run: call start\(\) first"):
        p.stats()  # (it returned {}, and stats()["frames"] a KeyError)
    p.start(wait=False)
    try:
        assert p.send(xyz, intensity=np.abs(xyz[:, 2]), rgb=np.zeros((5000, 3), np.uint8)) == 5000
        assert p.wait(None, until=lambda: not p.starting) is True  # wait says whether until came true
        assert p.wait(0.2, until=lambda: False) is False  # the time ran out
        st = p.stats()["stages"]
        assert all(v["ready"] for v in st.values()), {k: v["ready"] for k, v in st.items()}
        assert all(v["startup_ms"]["ready"] > 0 for k, v in st.items() if k != "api")
        p.wait(None, until=lambda: p.stats()["accounting"]["ingest_written"] >= 5000)
    finally:
        final = p.stop()
    assert final["accounting"]["ingest_written"] == 5000 and final["accounting"]["lost_before_ingest"] == 0
