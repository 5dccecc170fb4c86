"""The synthetic source's ``moving`` mode: clouds in the sensor frame plus transforms;
through the real source and ingest processes with ``frames.fixed: odom`` the ring holds the
same street as the ``world`` mode, and without frames the scans pile up at the sensor."""
import numpy as np

from ingest import ros_util as ru
from ingest.stage_util import IngestStage, base_config
from pointflow.frames.message import Transforms
from pointflow.ingest.transports import resolve_transport

OPTS = {"scans": 2, "realtime": False, "points_per_scan": 4000, "chunks_per_scan": 4, "drive_speed": 8.0,
        "channels": ["intensity"], "range_noise": 0.0, "moving_objects": 0}


def _world():
    cls = resolve_transport("synthetic")
    t = cls(cls.validate_options(dict(OPTS), "o"), "syn")
    t.open()
    return np.concatenate([c.positions for c in t.chunks() if c is not None])


def test_moving_mode_yields_transforms_before_each_cloud_it_needs():
    cls = resolve_transport("synthetic")
    t = cls(cls.validate_options({**OPTS, "mode": "moving"}, "o"), "syn")
    t.open()
    items = [x for x in t.chunks() if x is not None]
    assert isinstance(items[0], Transforms) and items[0].transforms[0].static
    newest = 0
    for x in items:
        if isinstance(x, Transforms):
            newest = max(tf.stamp_ns for tf in x.transforms)
        else:
            assert x.frame_id == "lidar" and 0 < x.stamp_ns < newest  # bracketed by /tf samples


def _run(frames):
    cfg = base_config()
    cfg["ring"]["extra_channels"] = ["intensity"]
    cfg["source"] = {"transport": "synthetic", "options": {**OPTS, "mode": "moving"}}
    cfg["frames"] = frames
    world = _world()
    st = ru.SourceIngest(cfg)
    try:
        st.wait_ingest(lambda s: s["points_out"] == world.shape[0] and "source" in st.done, timeout=120)
        for _ in range(5):  # the trace socket too (SourceIngest.poll reads only control)
            IngestStage.poll(st, 100)
        return world, st.ring.snapshot().positions, st
    finally:
        st.close()


def test_moving_mode_with_fixed_frame_rebuilds_the_world():
    world, got, st = _run({"fixed": "odom"})
    # the synthetic drive is continuous; tf2's lerp/slerp between 20 Hz samples of it is off
    # by at most yaw'' dt^2 / 8 * range (~2 mm at 60 m for the sway)
    assert np.abs(got - world).max() < 3e-3
    assert "transform" in {s[1] for s in st.spans}, {s[1] for s in st.spans}


def test_moving_mode_without_frames_piles_up_at_the_sensor():
    world, got, _ = _run({})
    assert np.abs(got - world).max() > 2.0  # sensor-frame points: the street smears without frames
