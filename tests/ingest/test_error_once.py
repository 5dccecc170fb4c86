"""A stage's fatal error reaches the user once (issue 31.5): a wrong ``ros2_zenoh`` topic used to
be printed by the source stage, the supervisor, the CLI and the summary line. Now one line, from
the supervisor, with the hint (the PointCloud2 topics that are published); the summary line only
says which stage failed. Real processes: a Zenoh router, a publisher behaving as rmw_zenoh's,
``pointflow run``."""
from __future__ import annotations

import pytest

pytest.importorskip("zenoh", reason="eclipse-zenoh comes with the remote extra: pip install 'pointflow[remote]'")
pytest.importorskip("rosbags", reason="rosbags comes with the ros extra: pip install 'pointflow[ros]'")

from pointflow.testing import rmw_zenoh_pub as P  # noqa: E402
from .test_ros2_zenoh import TOPIC, _run, source_cfg, start_publisher  # noqa: E402
from .test_ros2_zenoh import router  # noqa: E402,F401 - the fixture

HINT = "PointCloud2 topics published on domain 0: /front/points (1 publisher), /ouster/points (1 publisher)"


@pytest.mark.timeout(240)
def test_a_wrong_topic_is_printed_once_with_the_hint(tmp_path, router):  # noqa: F811
    pub = start_publisher(tmp_path, {"connect": router, "mode": "jazzy", "script": [],
                                     "advertise": [(TOPIC, P.PC2), ("/front/points", P.PC2)]})
    try:
        cfg = source_cfg(router, topic="/rear/points", discovery_timeout_s=2)
        cfg["render"]["output"] = {"dir": str(tmp_path / "out")}
        quiet = _run(tmp_path, cfg)
    finally:
        pub.close()
    out = quiet.stdout + quiet.stderr
    assert quiet.returncode == 2, (quiet.returncode, out[-3000:])
    assert "Traceback" not in out, out[-3000:]
    lines = [ln for ln in out.splitlines() if "/rear/points" in ln]
    assert len(lines) == 1, "\n".join(lines)
    assert "topic '/rear/points' has no publisher" in lines[0] and HINT in lines[0], lines[0]
    summary = [ln for ln in quiet.stdout.splitlines() if "FAILED" in ln]
    assert summary and "stage source" in summary[0], quiet.stdout
