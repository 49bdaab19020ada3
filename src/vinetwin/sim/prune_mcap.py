"""A vine's whole simulated job for the robotics viewers: a ROS 2 bag with MCAP storage (a folder
holding `NAME.mcap`), written with `rosbags`, which Foxglove opens (docs/ros.md). Message times
are the job's simulated time. ROS 2 message types, CDR encoded:

| topic | type | what |
|---|---|---|
| `/tf` | `tf2_msgs/TFMessage` | `vine` -> `base` (the platform's stop) and `vine` -> `camera` (the true camera) |
| `/joint_states` | `sensor_msgs/JointState` | the Panda's joints (`--sim mujoco`, and along transits) |
| `/vinetwin/events` | `diagnostic_msgs/DiagnosticStatus` | each phase's start (platform, transit, servo, cut, retreat, stow), each cut's outcome with its blade error, a skipped cut's reason (level 1) |
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vinetwin.conventions import ros_quat_xyzw
from vinetwin.errors import InputError
from vinetwin.frames import Array

TOPICS = {
    "/tf": "tf2_msgs/msg/TFMessage",
    "/joint_states": "sensor_msgs/msg/JointState",
    "/vinetwin/events": "diagnostic_msgs/msg/DiagnosticStatus",
}
JOINTS = tuple(f"panda_joint{i}" for i in range(1, 8))


@dataclass
class Track:
    """What the job did over its simulated time: poses (the base and the true camera in the
    vine frame, the joints when known) and events."""

    clock: float = 0.0
    """The job's simulated time now (s)."""
    poses: list[tuple[float, Array, Array, Array | None]] = field(default_factory=list)
    events: list[tuple[float, str, int]] = field(default_factory=list)

    def pose(self, t: float, T_vine_base: Array, T_vine_camera: Array, q: Any = None) -> None:
        self.poses.append((float(t), np.asarray(T_vine_base, float).copy(),
                           np.asarray(T_vine_camera, float).copy(),
                           None if q is None else np.asarray(q, float).copy()))  # fmt: skip

    def event(self, text: str, level: int = 0, t: float | None = None) -> None:
        self.events.append((self.clock if t is None else float(t), text, level))


def write_mcap(path: Path, track: Track) -> Path:
    """The track as a ROS 2 bag folder at `path` (refused if it exists); returns the folder."""
    try:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:
        raise InputError(f"MCAP logs need rosbags: pip install rosbags ({exc})") from exc
    if path.exists():
        raise InputError(f"{path} exists; choose a new folder for the MCAP")
    ts = get_typestore(Stores.ROS2_HUMBLE)
    M: dict[str, Any] = dict(ts.types)
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    conn = {t: writer.add_connection(t, m, typestore=ts) for t, m in TOPICS.items()}

    def header(t: float, frame: str) -> Any:
        ns = max(round(t * 1e9), 0)
        stamp = M["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        return M["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def tf(t: float, child: str, T: Array) -> Any:
        x, y, z, w = ros_quat_xyzw(T[:3, :3])
        tr = M["geometry_msgs/msg/Transform"](
            translation=M["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
            rotation=M["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
        )
        return M["geometry_msgs/msg/TransformStamped"](
            header=header(t, "vine"), child_frame_id=child, transform=tr
        )

    def write(topic: str, t: float, msg: Any) -> None:
        writer.write(conn[topic], max(round(t * 1e9), 0), ts.serialize_cdr(msg, TOPICS[topic]))

    items: list[tuple[float, int, Any]] = [(p[0], 0, p) for p in track.poses]
    items += [(e[0], 1, e) for e in track.events]
    try:
        for t, kind, item in sorted(items, key=lambda x: (x[0], x[1])):
            if kind == 0:
                _, B, C, q = item
                msg = M["tf2_msgs/msg/TFMessage"](transforms=[tf(t, "base", B), tf(t, "camera", C)])
                write("/tf", t, msg)
                if q is not None:
                    js = M["sensor_msgs/msg/JointState"](
                        header=header(t, "base"), name=list(JOINTS), position=np.asarray(q),
                        velocity=np.zeros(0), effort=np.zeros(0),
                    )  # fmt: skip
                    write("/joint_states", t, js)
            else:
                _, text, level = item
                status = M["diagnostic_msgs/msg/DiagnosticStatus"](
                    level=level, name="vinetwin prune", message=text, hardware_id="", values=[]
                )
                write("/vinetwin/events", t, status)
    finally:
        writer.close()
    return path
