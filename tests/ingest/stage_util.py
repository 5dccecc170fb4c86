"""Run the real ingest stage (``stage_main``) in a spawned process, without the full
supervisor: the test owns the ring and binds the control/trace endpoints itself (the rig is
``pointflow.testing.StageRig``, shared with bench/)."""
from __future__ import annotations

from pointflow.testing import StageRig, decode_spans  # noqa: F401  (decode_spans: tests import it here)


def base_config(**ring) -> dict:
    cfg = {"source": {"transport": "synthetic", "options": {"scans": 1, "realtime": False}},
           "ring": {"max_points": 200_000, **ring},
           "render": {"backend": "cpu", "color_by": "intensity", "output": {"dir": None}},
           "supervisor": {"heartbeat_ms": 50}}
    return cfg


class IngestStage(StageRig):
    """A live ingest process plus the test's ends of its sockets (``push`` feeds it)."""

    def __init__(self, cfg: dict, ring_channels=None):
        super().__init__(cfg, "ingest", ring_channels=ring_channels)
        self.push = self.sender()  # tests want every message delivered
        self.done = False
