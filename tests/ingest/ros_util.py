"""Test helpers for the ROS paths: PointCloud2 clouds packed point by point with ``struct``
(independent of the decoder's numpy views), bags written with the ``rosbags`` writers, a
rosbridge v2 server in its own process, and a source + ingest pair of real stage processes
feeding a ring the test reads."""
from __future__ import annotations

import base64
import dataclasses
import json
import multiprocessing as mp
import os
import struct
import time
from pathlib import Path
from typing import Any

import numpy as np

from pointflow.runtime.stage import stage_main
from pointflow.stage.context import RunInfo

from .stage_util import IngestStage

# datatype -> (struct code, numpy dtype)
DT = {1: ("b", np.int8), 2: ("B", np.uint8), 3: ("h", np.int16), 4: ("H", np.uint16), 5: ("i", np.int32),
      6: ("I", np.uint32), 7: ("f", np.float32), 8: ("d", np.float64)}
PAD = 0xAB  # padding bytes are garbage, never zeros: a decoder reading them shows


@dataclasses.dataclass
class Cloud:
    """One PointCloud2: layout, ground-truth values per field and the packed bytes."""

    fields: list[tuple[str, int, int, int]]  # name, offset, datatype, count (in the order listed)
    point_step: int
    width: int
    height: int
    row_step: int
    big: bool
    values: dict[str, np.ndarray]
    data: bytes
    stamp: tuple[int, int] = (1700000000, 123456789)

    @property
    def n(self) -> int:
        return self.width * self.height

    @property
    def stamp_ns(self) -> int:
        return self.stamp[0] * 1_000_000_000 + self.stamp[1]

    def as_dict(self, ros1: bool = False, data: Any = None) -> dict:
        """The rosbridge form (``data`` bytes unless given)."""
        st = {"secs": self.stamp[0], "nsecs": self.stamp[1]} if ros1 else {"sec": self.stamp[0], "nanosec": self.stamp[1]}
        return {"header": {"stamp": st, "frame_id": "lidar"}, "height": self.height, "width": self.width,
                "fields": [{"name": nm, "offset": o, "datatype": d, "count": c} for nm, o, d, c in self.fields],
                "is_bigendian": self.big, "point_step": self.point_step, "row_step": self.row_step,
                "data": self.data if data is None else data, "is_dense": False}

    def ros_msg(self, ts):
        """A rosbags message of typestore ``ts``."""
        T = ts.types
        hdr = T["std_msgs/msg/Header"]
        extra = {"seq": 0} if "seq" in hdr.__dataclass_fields__ else {}
        return T["sensor_msgs/msg/PointCloud2"](
            header=hdr(**extra, stamp=T["builtin_interfaces/msg/Time"](sec=self.stamp[0], nanosec=self.stamp[1]),
                       frame_id="lidar"),
            height=self.height, width=self.width,
            fields=[T["sensor_msgs/msg/PointField"](name=nm, offset=o, datatype=d, count=c) for nm, o, d, c in self.fields],
            is_bigendian=self.big, point_step=self.point_step, row_step=self.row_step,
            data=np.frombuffer(self.data, np.uint8), is_dense=False)

    def expected(self, keep_nan: bool = True) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Positions (N, 3) and channels as the decoder must produce them, from the values
        the bytes were packed from; packed colours unpacked with Python integer ops."""
        v = self.values
        pos = np.column_stack([v["x"], v["y"], v["z"]])
        ch: dict[str, np.ndarray] = {}
        for nm, _, _, _ in self.fields:
            if nm in ("x", "y", "z"):
                continue
            if nm in ("rgb", "rgba"):
                bits = [int(u) for u in v[nm].view(np.uint32)]
                ch["rgb"] = np.array([[(b >> 16) & 255, (b >> 8) & 255, b & 255] for b in bits], np.uint8)
            else:
                ch[nm] = v[nm]
        if not keep_nan:
            ok = np.isfinite(pos).all(axis=1)
            pos, ch = pos[ok], {k: a[ok] for k, a in ch.items()}
        return pos, ch


def pack(fields, point_step, width, height, values, big=False, row_pad=0, stamp=(1700000000, 123456789)) -> Cloud:
    """Pack ``values`` point by point with ``struct`` (padding bytes = 0xAB)."""
    row_step = width * point_step + row_pad
    buf = bytearray([PAD]) * (row_step * height)
    end = ">" if big else "<"
    for r in range(height):
        for c in range(width):
            i = r * width + c
            base = r * row_step + c * point_step
            for nm, off, dt, count in fields:
                code = DT[dt][0]
                val = values[nm][i]
                if nm in ("rgb", "rgba"):  # packed colour: write the uint32 bits
                    struct.pack_into(end + "I", buf, base + off, int(np.asarray(val).view(np.uint32)))
                elif count == 1:
                    struct.pack_into(end + code, buf, base + off, val.item())
                else:
                    struct.pack_into(end + code * count, buf, base + off, *[x.item() for x in val])
    return Cloud(list(fields), point_step, width, height, row_step, big, values, bytes(buf), stamp)


def _coords(rng, n, dtype=np.float32):
    """Multiples of 1/1024 within +-100: the ring's float32 offsets hold them exactly."""
    return (rng.integers(-102400, 102400, n) / 1024.0).astype(dtype)


def cloud_padded(seed=0, n=64) -> Cloud:
    """Ouster-like: 48-byte points, x y z + 4 pad bytes, then intensity, t, reflectivity, ring, ambient, range."""
    rng = np.random.default_rng(seed)
    f = [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("intensity", 16, 7, 1), ("t", 20, 6, 1),
         ("reflectivity", 24, 4, 1), ("ring", 26, 4, 1), ("ambient", 28, 4, 1), ("range", 32, 6, 1)]
    v = {"x": _coords(rng, n), "y": _coords(rng, n), "z": _coords(rng, n),
         "intensity": (rng.integers(0, 4096, n) / 16).astype(np.float32), "t": rng.integers(0, 100_000, n).astype(np.uint32),
         "reflectivity": rng.integers(0, 65535, n).astype(np.uint16), "ring": (np.arange(n) % 128).astype(np.uint16),
         "ambient": rng.integers(0, 65535, n).astype(np.uint16), "range": rng.integers(0, 1 << 24, n).astype(np.uint32)}
    return pack(f, 48, n, 1, v, stamp=(1700000000 + seed, 1000 * seed))


def cloud_bigendian(seed=1, n=40) -> Cloud:
    """Big-endian float64 x y z, uint16 intensity, int8 ring, 4 pad bytes."""
    rng = np.random.default_rng(seed)
    f = [("x", 0, 8, 1), ("y", 8, 8, 1), ("z", 16, 8, 1), ("intensity", 24, 4, 1), ("ring", 26, 1, 1)]
    v = {"x": _coords(rng, n, np.float64), "y": _coords(rng, n, np.float64), "z": _coords(rng, n, np.float64),
         "intensity": rng.integers(0, 65535, n).astype(np.uint16), "ring": rng.integers(-128, 127, n).astype(np.int8)}
    return pack(f, 32, n, 1, v, big=True, stamp=(1700000100 + seed, 7))


def cloud_unsorted(seed=2, n=33) -> Cloud:
    """Fields listed out of offset order, x y z not adjacent (y before x, intensity between)."""
    rng = np.random.default_rng(seed)
    f = [("z", 12, 7, 1), ("intensity", 8, 7, 1), ("ring", 16, 3, 1), ("x", 4, 7, 1), ("y", 0, 7, 1)]
    v = {"x": _coords(rng, n), "y": _coords(rng, n), "z": _coords(rng, n),
         "intensity": (rng.integers(0, 1000, n) / 4).astype(np.float32), "ring": rng.integers(-300, 300, n).astype(np.int16)}
    return pack(f, 20, n, 1, v, stamp=(1700000200 + seed, 9))


def cloud_count(seed=3, n=25) -> Cloud:
    """A count > 1 field (normal x3 float32) and a uint8 x2 label field."""
    rng = np.random.default_rng(seed)
    f = [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("normal", 12, 7, 3), ("label", 24, 2, 2)]
    v = {"x": _coords(rng, n), "y": _coords(rng, n), "z": _coords(rng, n),
         "normal": (rng.integers(-512, 512, (n, 3)) / 512).astype(np.float32), "label": rng.integers(0, 255, (n, 2)).astype(np.uint8)}
    return pack(f, 28, n, 1, v, stamp=(1700000300 + seed, 11))


def cloud_organised(seed=4, width=16, height=4) -> Cloud:
    """Organised (height > 1), padded rows (row_step > width * point_step), NaN rows and NaN points."""
    rng = np.random.default_rng(seed)
    n = width * height
    f = [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), ("intensity", 12, 7, 1)]
    v = {"x": _coords(rng, n), "y": _coords(rng, n), "z": _coords(rng, n),
         "intensity": (rng.integers(0, 255, n)).astype(np.float32)}
    v["x"][width:2 * width] = np.nan  # row 1: no returns
    v["y"][width:2 * width] = np.nan
    v["z"][width:2 * width] = np.nan
    v["z"][3::7] = np.nan             # scattered misses
    return pack(f, 16, width, height, v, row_pad=24, stamp=(1700000400 + seed, 13))


def _packed(rgb: np.ndarray, alpha: int) -> np.ndarray:
    u = (np.uint32(alpha) << 24) | (rgb[:, 0].astype(np.uint32) << 16) | (rgb[:, 1].astype(np.uint32) << 8) | rgb[:, 2]
    return u.astype(np.uint32).view(np.float32)


def cloud_rgb(seed=5, n=30, rgba=False, big=False) -> Cloud:
    """PCL-packed colour as float32: ``rgb`` 0x00RRGGBB, or ``rgba`` with alpha 0xFF (the float
    bits are then NaN patterns, which must survive)."""
    rng = np.random.default_rng(seed)
    col = rng.integers(0, 256, (n, 3)).astype(np.uint8)
    name = "rgba" if rgba else "rgb"
    f = [("x", 0, 7, 1), ("y", 4, 7, 1), ("z", 8, 7, 1), (name, 16, 7, 1)]
    v = {"x": _coords(rng, n), "y": _coords(rng, n), "z": _coords(rng, n), name: _packed(col, 255 if rgba else 0)}
    return pack(f, 32 if not rgba else 20, n, 1, v, big=big, stamp=(1700000500 + seed, 15))


def all_clouds() -> dict[str, Cloud]:
    return {"/os/points": cloud_padded(), "/be": cloud_bigendian(), "/unsorted": cloud_unsorted(),
            "/count": cloud_count(), "/organised": cloud_organised(), "/rgb": cloud_rgb(), "/rgba": cloud_rgb(6, rgba=True)}


def broken(kind: str, seed: int = 9) -> Cloud:
    """A cloud the decoder must reject, one per reason."""
    c = cloud_padded(seed, n=8)
    if kind == "truncated":
        return dataclasses.replace(c, data=c.data[:-5])
    if kind == "field_overflow":
        return dataclasses.replace(c, fields=c.fields[:-1] + [("range", 46, 6, 1)])
    if kind == "unknown_datatype":
        return dataclasses.replace(c, fields=c.fields[:3] + [("intensity", 16, 9, 1)])
    if kind == "no_xyz":
        return dataclasses.replace(c, fields=[f for f in c.fields if f[0] != "z"])
    raise ValueError(kind)


REJECT_KINDS = ("truncated", "field_overflow", "unknown_datatype", "no_xyz")

# ----------------------------------------------------------------------------- bags
PC2 = "sensor_msgs/msg/PointCloud2"


def write_bag(path: Path, kind: str, messages: list[tuple[str, int, Cloud]], extra_string_topic: bool = True,
              compression: str = "") -> Path:
    """Write ``(topic, bag time ns, cloud)`` messages with the rosbags writers.

    kind: ``ros1`` (.bag), ``sqlite3`` / ``mcap`` (ROS 2 bag folders), ``bare_mcap`` (the
    .mcap file of a ROS 2 MCAP bag, on its own), ``bare_db3`` (likewise). compression: ROS 1 ``bz2``/``lz4`` chunks,
    ROS 2 ``file``/``message`` (zstd)."""
    from rosbags.typesys import Stores, get_typestore

    if kind == "ros1":
        from rosbags.rosbag1 import Writer
        ts = get_typestore(Stores.ROS1_NOETIC)
        w = Writer(path)
        if compression:
            w.set_compression(getattr(Writer.CompressionFormat, compression.upper()))
        ser = lambda m: ts.serialize_ros1(m, PC2)  # noqa: E731
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.rosbag2.enums import CompressionFormat, CompressionMode
        ts = get_typestore(Stores.ROS2_HUMBLE)
        folder = path.with_suffix("") if kind in ("bare_mcap", "bare_db3") else path
        plugin = StoragePlugin.SQLITE3 if kind in ("sqlite3", "bare_db3") else StoragePlugin.MCAP
        w = Writer(folder, version=9, storage_plugin=plugin)
        if compression:
            w.set_compression(getattr(CompressionMode, compression.upper()), CompressionFormat.ZSTD)
        ser = lambda m: ts.serialize_cdr(m, PC2)  # noqa: E731
    with w:
        conns = {}
        for topic, _, _ in messages:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, PC2, typestore=ts)
        if extra_string_topic:
            sc = w.add_connection("/chatter", "std_msgs/msg/String", typestore=ts)
            s = ts.types["std_msgs/msg/String"](data="hello")
            w.write(sc, messages[0][1], ts.serialize_ros1(s, "std_msgs/msg/String") if kind == "ros1"
                    else ts.serialize_cdr(s, "std_msgs/msg/String"))
        for topic, t_ns, cloud in messages:
            w.write(conns[topic], t_ns, ser(cloud.ros_msg(ts)))
    if kind in ("bare_mcap", "bare_db3"):
        folder = path.with_suffix("")
        (folder / f"{folder.name}{path.suffix}").rename(path)
    return path


def strip_definitions(folder: Path) -> None:
    """Make a ROS 2 sqlite3 bag look like one recorded by Humble or older: no message
    definitions, no type hashes (rosbag2 only began storing them with Iron)."""
    import re
    import sqlite3

    db = sqlite3.connect(next(folder.glob("*.db3")))
    db.execute("DELETE FROM message_definitions")
    db.execute("UPDATE topics SET type_description_hash = ''")
    db.commit()
    db.close()
    meta = folder / "metadata.yaml"
    meta.write_text(re.sub(r"type_description_hash:[^\n]*\n\s*RIHS01_[0-9a-f]+\n", "type_description_hash: ''\n",
                           meta.read_text()))
    assert "RIHS01" not in meta.read_text()


# ----------------------------------------------------------------------------- source + ingest
class SourceIngest(IngestStage):
    """The real source stage (this config's transport) and the real ingest stage, each in
    its own process, feeding a ring this test owns."""

    def __init__(self, cfg: dict):
        super().__init__(cfg)
        self.stage_stats: dict[str, dict] = {}
        self.done: set[str] = set()
        info = RunInfo(run_dir=self.run_dir, endpoints=self.endpoints, ring_name="", slab_names=("", ""),
                       out_dir=None, supervisor_pid=os.getpid(), source_index=0)
        self.src = mp.get_context("spawn").Process(target=stage_main, args=("source", "source", cfg, os.getcwd(), info),
                                                   daemon=True)
        self.src.start()

    def on_control(self, m: dict) -> None:
        if m.get("type") == "heartbeat":
            self.stage_stats[m["stage"]] = m["stats"]
            if m["stage"] == "ingest":
                self.last = m["stats"]
        elif m.get("type") == "done":
            self.done.add(m["stage"])
        else:
            super().on_control(m)

    def wait_ingest(self, pred, timeout: float = 60.0) -> dict:
        return self.wait_stats(pred, timeout)

    def close(self) -> None:
        if self.src.is_alive():
            self.src.terminate()
        self.src.join(10)
        if self.src.is_alive():
            self.src.kill()
            self.src.join(5)
        super().close()


# ----------------------------------------------------------------------------- rosbridge server
def _serve(port: int, script: list, events) -> None:
    """A rosbridge v2 server (websockets' sync server) in its own process: per connection it
    waits for ``subscribe``, reports it, sends ``script`` ((kind, payload) pairs: ``text``
    or ``bin`` frames), then reports every later client message (``unsubscribe``)."""
    from websockets.sync.server import serve

    def handler(ws):
        try:
            sub = json.loads(ws.recv(timeout=10))
            events.put(("client", sub))
            for kind, payload in script:
                ws.send(payload)
            events.put(("sent", len(script)))
            while True:
                events.put(("client", json.loads(ws.recv())))
        except Exception:  # noqa: BLE001 - the client went away
            pass

    with serve(handler, "127.0.0.1", port, max_size=None, compression=None) as server:
        events.put(("listening", port))
        server.serve_forever()


class RosbridgeServer:
    def __init__(self, port: int, script: list):
        ctx = mp.get_context("spawn")
        self.events = ctx.Queue()
        self.proc = ctx.Process(target=_serve, args=(port, script, self.events), daemon=True)
        self.proc.start()
        kind, _ = self.events.get(timeout=30)
        assert kind == "listening"
        self.client_messages: list[dict] = []
        self.sent = 0

    def drain(self, timeout: float = 0.0) -> None:
        end = time.monotonic() + timeout
        while True:
            try:
                kind, val = self.events.get(timeout=max(0.01, end - time.monotonic()))
            except Exception:  # noqa: BLE001 - queue.Empty
                return
            if kind == "client":
                self.client_messages.append(val)
            elif kind == "sent":
                self.sent += 1

    def kill(self) -> None:
        """Drop the server abruptly (the robot went away)."""
        self.proc.kill()
        self.proc.join(10)

    def close(self) -> None:
        if self.proc.is_alive():
            self.proc.terminate()
            self.proc.join(10)
        self.events.close()
        self.events.join_thread()


def publish_json(topic: str, cloud: Cloud, ros1: bool = True) -> str:
    """``compression: none``: a JSON text frame, data in base64 (ROS 1 stamp names)."""
    body = cloud.as_dict(ros1=ros1, data=base64.b64encode(cloud.data).decode())
    return json.dumps({"op": "publish", "topic": topic, "msg": body})


def publish_cbor(topic: str, cloud: Cloud) -> bytes:
    """``compression: cbor``: a binary frame, data a CBOR byte string."""
    import cbor2
    return cbor2.dumps({"op": "publish", "topic": topic, "msg": cloud.as_dict(ros1=False)})
