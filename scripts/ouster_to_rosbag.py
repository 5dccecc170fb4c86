"""Write the real Ouster OS-1-128 scans of ``../shared/data/ouster_os1_128`` as a ROS recording
(``sensor_msgs/PointCloud2`` on ``/ouster/points``, the ouster-ros driver's 48-byte point
layout, organised 128 x 1024 with NaN for beams without a return, 10 Hz), so
``configs/rosbag.yaml`` has something real to replay without ROS.

    .venv/bin/python scripts/ouster_to_rosbag.py [--out out/ouster-ros2] [--storage mcap|sqlite3|ros1]
"""
from __future__ import annotations

import argparse
import glob
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
# ouster-ros PointOS (x y z pad, intensity, t, reflectivity, ring, ambient, range), 48 bytes
FIELDS = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7), ("t", 20, 6), ("reflectivity", 24, 4),
          ("ring", 26, 4), ("ambient", 28, 4), ("range", 32, 6)]
CODES = {4: "<u2", 6: "<u4", 7: "<f4"}
H, W = 128, 1024


def scan_bytes(path: str) -> bytes:
    with np.load(path) as z:
        xyz, refl, rng, nir = z["xyz"], z["reflectivity"], z["range"], z.get("near_ir")
    rec = np.zeros(H * W, dtype={"names": [f[0] for f in FIELDS], "formats": [CODES[f[2]] for f in FIELDS],
                                 "offsets": [f[1] for f in FIELDS], "itemsize": 48})
    m = min(xyz.shape[0], H * W)
    for j, k in enumerate("xyz"):
        rec[k][:m] = xyz[:m, j]
        rec[k][m:] = np.nan  # the npz dropped range-0 beams: no return, as the driver marks them
    rec["reflectivity"][:m] = refl[:m]
    rec["intensity"][:m] = refl[:m]
    rec["range"][:m] = rng[:m]
    if nir is not None:
        rec["ambient"][:m] = nir[:m]
    rec["ring"] = np.arange(H * W) // W
    return rec.tobytes()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT.parent / "shared" / "data" / "ouster_os1_128"))
    ap.add_argument("--out", default=str(ROOT / "out" / "ouster-ros2"))
    ap.add_argument("--storage", choices=["mcap", "sqlite3", "ros1"], default="mcap")
    args = ap.parse_args()
    files = sorted(glob.glob(os.path.join(args.data, "*.npz")))
    if not files:
        sys.exit(f"no .npz scans in {args.data} (see ../shared/data/MANIFEST.md)")
    from rosbags.typesys import Stores, get_typestore

    out = Path(args.out + (".bag" if args.storage == "ros1" and not args.out.endswith(".bag") else ""))
    if out.exists():
        sys.exit(f"{out} exists; remove it first")
    out.parent.mkdir(parents=True, exist_ok=True)
    if args.storage == "ros1":
        from rosbags.rosbag1 import Writer
        ts = get_typestore(Stores.ROS1_NOETIC)
        writer, ser = Writer(out), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer
        ts = get_typestore(Stores.ROS2_HUMBLE)
        plugin = StoragePlugin.MCAP if args.storage == "mcap" else StoragePlugin.SQLITE3
        writer, ser = Writer(out, version=9, storage_plugin=plugin), ts.serialize_cdr
    T = ts.types
    typ = "sensor_msgs/msg/PointCloud2"
    t0 = 1_700_000_000 * 10**9
    with writer as w:
        conn = w.add_connection("/ouster/points", typ, typestore=ts)
        for k, f in enumerate(files):
            t = t0 + k * 100_000_000  # 10 Hz
            hdr = T["std_msgs/msg/Header"](**({"seq": k} if args.storage == "ros1" else {}),
                                           stamp=T["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9),
                                           frame_id="os_sensor")
            msg = T["sensor_msgs/msg/PointCloud2"](
                header=hdr, height=H, width=W,
                fields=[T["sensor_msgs/msg/PointField"](name=n, offset=o, datatype=d, count=1) for n, o, d in FIELDS],
                is_bigendian=False, point_step=48, row_step=48 * W, data=np.frombuffer(scan_bytes(f), np.uint8),
                is_dense=False)
            w.write(conn, t, ser(msg, typ))
    print(f"wrote {len(files)} scans to {out}")


if __name__ == "__main__":
    main()
