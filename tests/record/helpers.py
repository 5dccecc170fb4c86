"""Reading recordings back without pointflow's code: the ``mcap`` library's readers, the
``mcap-ros2-support`` CDR decoder, and a numpy view of the PointCloud2 fields written here."""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import numpy as np
import pytest

from pointflow.testing import free_port as free_tcp_port  # noqa: F401  (tests import it here)
from pointflow.testing import wait_for  # noqa: F401  (tests import it here)

# PointField datatype -> numpy type (sensor_msgs/PointField constants)
NP = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}


@dataclass
class Msg:
    topic: str
    log_time: int
    publish_time: int
    sequence: int
    stamp_ns: int
    frame_id: str
    positions: np.ndarray
    channels: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        return self.positions.shape[0]


def _points(m) -> tuple[np.ndarray, dict]:
    """Positions (float64) and channels of a decoded PointCloud2 (one structured view)."""
    end = ">" if m.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for f in m.fields:
        code = end + NP[f.datatype]
        if f.name == "rgb":
            code = end + "u4"  # packed 0x00RRGGBB
        names.append(f.name)
        formats.append(np.dtype(code) if f.count == 1 else np.dtype((code, (f.count,))))
        offsets.append(f.offset)
    dt = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": m.point_step})
    a = np.frombuffer(bytes(m.data), dt, count=m.width * m.height)
    pos = np.column_stack([a["x"].astype(np.float64), a["y"].astype(np.float64), a["z"].astype(np.float64)])
    chans = {}
    for f in m.fields:
        if f.name in "xyz":
            continue
        v = a[f.name].copy()
        if f.name == "rgb":
            v = np.column_stack([(v >> 16) & 255, (v >> 8) & 255, v & 255]).astype(np.uint8)
        chans[f.name] = v
    return pos, chans


def read_recording(path: str, tolerant: bool = False) -> list[Msg]:
    """Every message in file order. ``tolerant``: the file may be cut short (no summary): read
    record by record up to the cut, as the mcap library's streaming reader does."""
    from mcap.exceptions import McapError
    from mcap.reader import NonSeekingReader, make_reader
    from mcap_ros2.decoder import DecoderFactory

    out = []
    dec = DecoderFactory()
    decoders = {}
    with open(path, "rb") as f:
        reader = NonSeekingReader(f) if tolerant else make_reader(f)
        it = reader.iter_messages(log_time_order=False)
        try:
            for schema, channel, msg in it:
                d = decoders.get(schema.id)
                if d is None:
                    d = decoders[schema.id] = dec.decoder_for(channel.message_encoding, schema)
                m = d(msg.data)
                pos, chans = _points(m)
                out.append(Msg(channel.topic, msg.log_time, msg.publish_time, msg.sequence,
                               m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec, m.header.frame_id,
                               pos, chans))
        except McapError:
            if not tolerant:
                raise
    return out


def summary_intact(path: str) -> bool:
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            return make_reader(f).get_summary() is not None
    except Exception:  # noqa: BLE001
        return False


def ci() -> bool:
    return os.environ.get("CI", "").lower() in ("1", "true", "yes")


def require_root(what: str) -> None:
    """Skip without root; under CI=true fail instead (CI must run these)."""
    if os.geteuid() != 0:
        if ci():
            pytest.fail(f"CI=true but {what} needs root")
        pytest.skip(f"{what} needs root")




