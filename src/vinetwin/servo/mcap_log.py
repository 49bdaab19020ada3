"""A servo run for the robotics viewers: a ROS 2 bag with MCAP storage (a folder holding
`NAME.mcap` and `metadata.yaml`), written with `rosbags`, which Foxglove opens and
`ros2 bag play` plays into RViz (docs/ros.md). ROS 2 message types, CDR encoded:

| topic | type | what | messages |
|---|---|---|---|
| `/tf_static` | `tf2_msgs/TFMessage` | `base` -> `goal` (the reference camera) and `base` -> `cut_point` | 1 |
| `/tf` | `tf2_msgs/TFMessage` | `base` -> `camera`, the robot's camera pose for the frame | 1 per frame with a pose |
| `/vinetwin/reference_cloud` | `sensor_msgs/PointCloud2` | the reference cloud, frame `goal` | 1 |
| `/vinetwin/live_cloud` | `sensor_msgs/PointCloud2` | the frame after perception, frame `camera` | 1 per frame perceived |
| `/vinetwin/twist` | `geometry_msgs/TwistStamped` | the twist sent (camera frame; zero when refused) | 1 per frame |
| `/vinetwin/trust` | `diagnostic_msgs/DiagnosticStatus` | level 0 trusted, 1 refused; the reason; ICP figures | 1 per frame |

Message times are the frames' stamps (simulated time in simulation).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from vinetwin.cloud import Cloud
from vinetwin.conventions import ros_quat_xyzw
from vinetwin.errors import InputError
from vinetwin.frames import Array
from vinetwin.servo.loop import Cycle

TOPICS = {
    "/tf_static": "tf2_msgs/msg/TFMessage",
    "/tf": "tf2_msgs/msg/TFMessage",
    "/vinetwin/reference_cloud": "sensor_msgs/msg/PointCloud2",
    "/vinetwin/live_cloud": "sensor_msgs/msg/PointCloud2",
    "/vinetwin/twist": "geometry_msgs/msg/TwistStamped",
    "/vinetwin/trust": "diagnostic_msgs/msg/DiagnosticStatus",
}


class McapLog:
    """Writes a servo run as MCAP; `cycle(c)` per loop cycle, `close()` at the end."""

    def __init__(
        self, path: str | Path, reference: Cloud, T_base_goal: Array, T_base_cut: Array
    ) -> None:
        try:
            from rosbags.rosbag2 import StoragePlugin, Writer
            from rosbags.typesys import Stores, get_typestore
        except ImportError as exc:
            raise InputError(f"MCAP logs need rosbags: pip install rosbags ({exc})") from exc
        self.path = Path(path)
        if self.path.exists():
            raise InputError(f"--mcap {self.path} exists; choose a new name (a folder is made)")
        self.ts = get_typestore(Stores.ROS2_HUMBLE)
        self.T: dict[str, Any] = dict(self.ts.types)  # message classes, built at run time
        self.writer: Any = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        self.writer.open()
        self.conn = {
            t: self.writer.add_connection(t, m, typestore=self.ts) for t, m in TOPICS.items()
        }
        self.reference = reference
        self.T_base_goal = np.asarray(T_base_goal, float)
        self.T_base_cut = np.asarray(T_base_cut, float)
        self._started = False

    @property
    def mcap_file(self) -> Path:
        """The .mcap file inside the bag folder."""
        return next(self.path.glob("*.mcap"))

    # ------------------------------------------------------------------ messages
    def _header(self, t: float, frame: str) -> Any:
        ns = max(round(t * 1e9), 0)
        stamp = self.T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        return self.T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def _tf(self, t: float, parent: str, child: str, T: Array) -> Any:
        x, y, z, w = ros_quat_xyzw(T[:3, :3])
        tr = self.T["geometry_msgs/msg/Transform"](
            translation=self.T["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
            rotation=self.T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
        )
        return self.T["geometry_msgs/msg/TransformStamped"](
            header=self._header(t, parent), child_frame_id=child, transform=tr
        )

    def _cloud(self, t: float, frame: str, points: Array) -> Any:
        pts = np.ascontiguousarray(np.asarray(points, dtype="<f4").reshape(-1, 3))
        field = self.T["sensor_msgs/msg/PointField"]
        fields = [field(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")]
        return self.T["sensor_msgs/msg/PointCloud2"](
            header=self._header(t, frame), height=1, width=len(pts), fields=fields,
            is_bigendian=False, point_step=12, row_step=12 * len(pts),
            data=np.frombuffer(pts.tobytes(), np.uint8), is_dense=True,
        )  # fmt: skip

    def _write(self, topic: str, t: float, msg: Any) -> None:
        data = self.ts.serialize_cdr(msg, TOPICS[topic])
        self.writer.write(self.conn[topic], max(round(t * 1e9), 0), data)

    # ------------------------------------------------------------------ per cycle
    def cycle(self, c: Cycle) -> None:
        t = c.frame.stamp
        if not self._started:
            self._started = True
            statics = [
                self._tf(t, "base", "goal", self.T_base_goal),
                self._tf(t, "base", "cut_point", self.T_base_cut),
            ]
            self._write("/tf_static", t, self.T["tf2_msgs/msg/TFMessage"](transforms=statics))
            self._write(
                "/vinetwin/reference_cloud", t, self._cloud(t, "goal", self.reference.points)
            )
        if c.T_base_camera is not None:
            tf = self._tf(t, "base", "camera", np.asarray(c.T_base_camera, float))
            self._write("/tf", t, self.T["tf2_msgs/msg/TFMessage"](transforms=[tf]))
        r = c.result
        if r.cloud is not None:
            self._write("/vinetwin/live_cloud", t, self._cloud(t, "camera", r.cloud.points))
        v = self.T["geometry_msgs/msg/Vector3"]
        sent = np.asarray(c.sent, float)
        twist = self.T["geometry_msgs/msg/Twist"](linear=v(*sent[:3]), angular=v(*sent[3:]))
        self._write(
            "/vinetwin/twist",
            t,
            self.T["geometry_msgs/msg/TwistStamped"](header=self._header(t, "camera"), twist=twist),
        )
        kv = self.T["diagnostic_msgs/msg/KeyValue"]
        values = [kv(key="overrun", value=str(c.overrun)), kv(key="at_goal", value=str(r.at_goal))]
        if r.icp is not None:
            values += [
                kv(key="fitness", value=f"{r.icp.fitness:.4f}"),
                kv(key="overlap", value=f"{r.icp.overlap:.4f}"),
                kv(key="inlier_rmse_mm", value=f"{1000 * r.icp.inlier_rmse:.3f}"),
            ]
        status = self.T["diagnostic_msgs/msg/DiagnosticStatus"](
            level=0 if r.trusted and not c.overrun else 1, name="vinetwin servo",
            message=r.reason or ("overrun" if c.overrun else "trusted"),
            hardware_id="", values=values,
        )  # fmt: skip
        self._write("/vinetwin/trust", t, status)

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None
