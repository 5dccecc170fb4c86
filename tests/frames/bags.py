"""Bags with clouds and /tf, /tf_static written by the test with the rosbags writers
(ROS 1 .bag, ROS 2 sqlite3 / MCAP folders)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

PC2 = "sensor_msgs/msg/PointCloud2"
TFM = "tf2_msgs/msg/TFMessage"


class BagWriter:
    def __init__(self, path: Path, kind: str):
        from rosbags.typesys import Stores, get_typestore

        self.kind = kind
        if kind == "ros1":
            from rosbags.rosbag1 import Writer
            from rosbags.typesys import get_types_from_msg
            self.ts = get_typestore(Stores.ROS1_NOETIC)  # has no tf2_msgs: registered from its definition
            self.ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TFM))
            self.w = Writer(path)
            self.ser = self.ts.serialize_ros1
        else:
            from rosbags.rosbag2 import StoragePlugin, Writer
            self.ts = get_typestore(Stores.ROS2_HUMBLE)
            plugin = StoragePlugin.SQLITE3 if kind == "sqlite3" else StoragePlugin.MCAP
            self.w = Writer(path, version=9, storage_plugin=plugin)
            self.ser = self.ts.serialize_cdr
        self.path = path
        self.conns: dict[str, object] = {}
        self.msgs: list[tuple[int, str, str, object]] = []

    def _header(self, stamp_ns: int, frame: str):
        T = self.ts.types
        hdr = T["std_msgs/msg/Header"]
        extra = {"seq": 0} if "seq" in hdr.__dataclass_fields__ else {}
        return hdr(**extra, stamp=T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9),
                   frame_id=frame)

    def cloud(self, topic: str, t_rec: int, stamp_ns: int, frame: str, pos: np.ndarray, fields: dict | None = None):
        """x y z float32 plus extra per-point fields {name: array} (uint32/float32/float64)."""
        T = self.ts.types
        fields = fields or {}
        codes = {np.dtype(np.uint32): 6, np.dtype(np.float32): 7, np.dtype(np.float64): 8}
        cols = [("x", pos[:, 0].astype("<f4")), ("y", pos[:, 1].astype("<f4")), ("z", pos[:, 2].astype("<f4"))]
        cols += [(k, v.astype(v.dtype.newbyteorder("<"))) for k, v in fields.items()]
        dt = np.dtype({"names": [c for c, _ in cols], "formats": [a.dtype for _, a in cols]})
        rec = np.empty(pos.shape[0], dt)
        for c, a in cols:
            rec[c] = a
        pf = [T["sensor_msgs/msg/PointField"](name=c, offset=dt.fields[c][1], datatype=codes[np.dtype(a.dtype.name)], count=1)
              for c, a in cols]
        msg = T[PC2](header=self._header(stamp_ns, frame), height=1, width=pos.shape[0], fields=pf, is_bigendian=False,
                     point_step=dt.itemsize, row_step=dt.itemsize * pos.shape[0],
                     data=np.frombuffer(rec.tobytes(), np.uint8), is_dense=True)
        self.msgs.append((t_rec, topic, PC2, msg))

    def tf(self, topic: str, t_rec: int, items: list[tuple[str, str, int, np.ndarray, tuple]]):
        """items: (parent, child, stamp_ns, translation, quaternion xyzw)."""
        T = self.ts.types
        tss = []
        for parent, child, stamp, tr, q in items:
            tss.append(T["geometry_msgs/msg/TransformStamped"](
                header=self._header(stamp, parent), child_frame_id=child,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=float(tr[0]), y=float(tr[1]), z=float(tr[2])),
                    rotation=T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))))
        self.msgs.append((t_rec, topic, TFM, T[TFM](transforms=tss)))

    def write(self) -> Path:
        with self.w:
            for _, topic, mt, _ in self.msgs:
                if topic not in self.conns:
                    self.conns[topic] = self.w.add_connection(topic, mt, typestore=self.ts)
            for t, topic, mt, msg in sorted(self.msgs, key=lambda m: m[0]):
                self.w.write(self.conns[topic], t, self.ser(msg, mt))
        return self.path
