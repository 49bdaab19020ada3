"""ROS recordings in: a ROS 1 `.bag`, a ROS 2 bag (a folder with `metadata.yaml` and `.db3` or
`.mcap` files, or one of those files) as the RealSense ROS driver records them, read with
`rosbags` (pure Python, no ROS installation), into a capture folder (docs/ros.md).

What is read (`RosTopics`; defaults: the driver's topics, ROS 1 `/camera/...` and ROS 2
`/camera/camera/...`, the first present wins):
- depth: `sensor_msgs/Image`, `16UC1` (millimetres, REP 118: kept bit-exact with a 1 mm depth
  unit) or `32FC1` (metres: stored in 0.1 mm counts); no-data pixels (0, NaN) stay 0;
- its `sensor_msgs/CameraInfo`: the intrinsics (K) of the capture's camera;
- colour (`rgb8`, `bgr8`, `rgba8`, `bgra8`), when present at the depth image's size, the frame
  nearest in time within half a frame period;
- the camera's pose in the robot base from `/tf` and `/tf_static`: the chain of transforms from
  the base (the TF tree's root above the camera, or `RosTopics.base_frame`) to the depth image's
  `header.frame_id`, each moving transform interpolated (linear, and slerp for the rotation) to
  the image's stamp. A recording whose TF does not reach the camera is imported without poses,
  and `RosImport.pose_problem` says why.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vinetwin.camera import CameraModel, d405
from vinetwin.capture.folder import CaptureWriter
from vinetwin.capture.topics import RosTopics
from vinetwin.conventions import T_from_ros
from vinetwin.errors import InputError
from vinetwin.frames import Array, interpolate

log = logging.getLogger(__name__)

#: The RealSense ROS driver's default namespaces: ROS 1 (realsense2_camera 2.x) and ROS 2
#: (realsense2_camera 4.x, camera name and namespace both "camera").
DEFAULT_NAMESPACES = ("/camera", "/camera/camera")


@dataclass
class RosImport:
    """What an import found."""

    path: Path
    frames: int = 0
    posed: int = 0
    """Frames with a camera pose from TF."""
    topics: dict[str, str] = field(default_factory=dict)
    base_frame: str = ""
    camera_frame: str = ""
    pose_problem: str = ""
    """Why frames have no pose ('' when all have one)."""
    depth_encoding: str = ""


def _reader(path: Path) -> Any:
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError as exc:  # a dependency of vinetwin; say what is missing
        raise InputError(f"reading ROS bags needs rosbags: pip install rosbags ({exc})") from exc
    if (
        path.is_file()
        and path.suffix in (".db3", ".mcap")
        and (path.parent / "metadata.yaml").exists()
    ):
        path = path.parent  # a ROS 2 bag is its folder
    return AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))


def is_ros_bag(path: str | Path) -> bool:
    """True for a ROS 1 bag or a ROS 2 bag (folder, or a file in one) with a depth image topic;
    False for what librealsense reads instead (its own recordings) or anything else."""
    p = Path(path)
    try:
        with _reader(p) as reader:
            return _pick_topics(reader, RosTopics(), quiet=True) is not None
    except Exception:
        return False


def _topics_of(reader: Any) -> dict[str, str]:
    return {c.topic: c.msgtype for c in reader.connections}


def _pick_topics(reader: Any, want: RosTopics, quiet: bool = False) -> dict[str, str] | None:
    topics = _topics_of(reader)
    images = [t for t, m in topics.items() if m == "sensor_msgs/msg/Image"]
    infos = [t for t, m in topics.items() if m == "sensor_msgs/msg/CameraInfo"]
    depth = want.depth_topic
    if not depth:
        cands = [f"{ns}/depth/image_rect_raw" for ns in DEFAULT_NAMESPACES]
        depth = next((t for t in cands if t in images), "")
        if not depth:
            depth = next((t for t in images if "depth" in t and "aligned" not in t), "")
    if depth not in images:
        if quiet:
            return None
        raise InputError(
            f"no depth image topic {depth or '(none found)'!r} in the recording; its image "
            f"topics: {', '.join(images) or 'none'} (name one with --depth-topic)"
        )
    ns = depth.rsplit("/", 1)[0]
    info = want.info_topic or f"{ns}/camera_info"
    if info not in infos:
        if quiet:
            return None
        raise InputError(
            f"no CameraInfo topic {info!r} for {depth}; its CameraInfo topics: "
            f"{', '.join(infos) or 'none'} (name one with --info-topic)"
        )
    color = want.color_topic
    if not color:
        root = ns.rsplit("/", 1)[0]
        color = next(
            (t for t in (f"{root}/color/image_rect_raw", f"{root}/color/image_raw") if t in images),
            "",
        )
    elif color not in images:
        raise InputError(
            f"no colour image topic {color!r} (--color-topic); image topics: {', '.join(images)}"
        )
    out = {"depth": depth, "camera_info": info}
    if color:
        out["color"] = color
    for tf in ("/tf", "/tf_static"):
        if topics.get(tf) == "tf2_msgs/msg/TFMessage":
            out[tf.strip("/")] = tf
    return out


def _stamp(header: Any) -> float:
    return float(header.stamp.sec) + 1e-9 * float(header.stamp.nanosec)


def _image_array(msg: Any) -> np.ndarray:
    enc = msg.encoding.lower()
    kinds = {
        "16uc1": ("u2", 1), "mono16": ("u2", 1), "32fc1": ("f4", 1), "rgb8": ("u1", 3),
        "bgr8": ("u1", 3), "rgba8": ("u1", 4), "bgra8": ("u1", 4), "mono8": ("u1", 1),
    }  # fmt: skip
    if enc not in kinds:
        raise InputError(f"image encoding {msg.encoding!r} is not read (16UC1, 32FC1, rgb8, ...)")
    kind, ch = kinds[enc]
    dt = np.dtype(kind).newbyteorder(">" if msg.is_bigendian else "<")
    row = np.frombuffer(bytes(msg.data), np.uint8).reshape(msg.height, msg.step)
    px = row[:, : msg.width * ch * dt.itemsize].copy().view(dt).reshape(msg.height, msg.width, ch)
    px = px.astype(dt.newbyteorder("="))
    return px[:, :, 0] if ch == 1 else px


def _rgb(msg: Any) -> np.ndarray | None:
    img = _image_array(msg)
    enc = msg.encoding.lower()
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, 2).astype(np.uint8)
    img = img[:, :, :3]
    return np.ascontiguousarray(img[:, :, ::-1] if enc.startswith("bgr") else img)


def _camera_from_info(msg: Any) -> CameraModel:
    K = np.asarray(getattr(msg, "k", None) if hasattr(msg, "k") else msg.K, float).reshape(3, 3)
    w, h = int(msg.width), int(msg.height)
    return d405(
        "848x480", width=w, height=h, fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]),
        cy=float(K[1, 2]), name=f"ROS CameraInfo {msg.header.frame_id}",
    )  # fmt: skip


# ----------------------------------------------------------------------------- TF
class TfTree:
    """Transforms from `/tf` (time series) and `/tf_static` (constant), parent -> child."""

    def __init__(self) -> None:
        self.parent: dict[str, str] = {}
        self.static: dict[str, Array] = {}
        self.moving: dict[str, tuple[list[float], list[Array]]] = {}

    def add(self, msg: Any, static: bool) -> None:
        for tr in msg.transforms:
            child = tr.child_frame_id.lstrip("/")
            self.parent[child] = tr.header.frame_id.lstrip("/")
            t, q = tr.transform.translation, tr.transform.rotation
            T = T_from_ros([t.x, t.y, t.z], [q.x, q.y, q.z, q.w])
            if static:
                self.static[child] = T
            else:
                ts, Ts = self.moving.setdefault(child, ([], []))
                ts.append(_stamp(tr.header))
                Ts.append(T)

    def root_of(self, frame: str) -> str:
        seen = {frame}
        while frame in self.parent:
            frame = self.parent[frame]
            if frame in seen:
                break
            seen.add(frame)
        return frame

    def lookup(self, base: str, frame: str, t: float) -> tuple[Array | None, str]:
        """T_base_frame at time t, or None and why not."""
        T = np.eye(4)
        f, hops = frame, 0
        while f != base:
            if f not in self.parent:
                return None, f"TF does not connect {frame!r} to {base!r} (no parent of {f!r})"
            if f in self.static:
                step = self.static[f]
            else:
                step = self._at(f, t)
                if step is None:
                    return None, f"no {self.parent[f]} -> {f} transform around t = {t:.3f} s"
            T = step @ T
            f = self.parent[f]
            hops += 1
            if hops > 64:
                return None, "TF has a loop"
        return T, ""

    def _at(self, child: str, t: float) -> Array | None:
        ts, Ts = self.moving.get(child, ([], []))
        if not ts:
            return None
        order = np.argsort(ts)
        tt = np.asarray(ts)[order]
        k = int(np.searchsorted(tt, t))
        if k < len(tt) and abs(tt[k] - t) < 1e-9:
            return Ts[order[k]]
        if k == 0 or k == len(tt):
            return None  # outside the recorded span
        t0, t1 = tt[k - 1], tt[k]
        return interpolate(Ts[order[k - 1]], Ts[order[k]], (t - t0) / (t1 - t0))


# ----------------------------------------------------------------------------- import
def read_ros_bag(
    path: str | Path,
    out: str | Path,
    topics: RosTopics | None = None,
    max_frames: int = 0,
) -> RosImport:
    """Writes the recording's depth frames (with colour and TF poses where present) as a
    capture folder `out`; returns what was found."""
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: no such recording")
    want = topics or RosTopics()
    rep = RosImport(Path(out))
    with _reader(p) as reader:
        chosen = _pick_topics(reader, want)
        assert chosen is not None
        rep.topics = chosen
        conns = {c.topic: c for c in reader.connections}
        tf = TfTree()
        info_msg = None
        colors: list[tuple[float, Any]] = []
        depth_msgs: list[Any] = []
        wanted = [conns[t] for t in chosen.values()]
        for conn, _ts, raw in reader.messages(connections=wanted):
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.topic == chosen["depth"]:
                if not max_frames or len(depth_msgs) < max_frames:
                    depth_msgs.append(msg)
            elif conn.topic == chosen["camera_info"]:
                info_msg = info_msg or msg
            elif conn.topic == chosen.get("color"):
                colors.append((_stamp(msg.header), msg))
            elif conn.msgtype == "tf2_msgs/msg/TFMessage":
                tf.add(msg, static=conn.topic == chosen.get("tf_static"))
    if info_msg is None:
        raise InputError(f"{p}: no message on {chosen['camera_info']}")
    if not depth_msgs:
        raise InputError(f"{p}: no message on {chosen['depth']}")
    camera = _camera_from_info(info_msg)
    first = depth_msgs[0]
    rep.depth_encoding = first.encoding
    unit = 0.001 if first.encoding.lower() in ("16uc1", "mono16") else 1e-4
    rep.camera_frame = first.header.frame_id.lstrip("/")
    rep.base_frame = want.base_frame or tf.root_of(rep.camera_frame)
    stamps = [_stamp(m.header) for m in depth_msgs]
    period = float(np.median(np.diff(stamps))) if len(stamps) > 1 else 0.1
    writer = CaptureWriter(
        out, camera, unit,
        extra={"provenance": {"ros_bag": str(p), "topics": chosen, "base_frame": rep.base_frame,
                              "camera_frame": rep.camera_frame}},
    )  # fmt: skip
    problems: list[str] = []
    for msg, t in zip(depth_msgs, stamps, strict=True):
        img = _image_array(msg)
        if (img.shape[1], img.shape[0]) != (camera.width, camera.height):
            raise InputError(
                f"{p}: a depth image of {img.shape[1]}x{img.shape[0]} on {chosen['depth']}, but "
                f"its CameraInfo says {camera.width}x{camera.height}"
            )
        if unit == 0.001:
            counts = img.astype(np.uint16)  # millimetres, bit-exact
        else:
            d = img.astype(np.float64)
            ok = np.isfinite(d) & (d > 0)
            counts = np.where(ok, np.clip(np.round(np.where(ok, d, 0) / unit), 0, 65535), 0)
            counts = counts.astype(np.uint16)
        color = None
        if colors:
            ct, cm = min(colors, key=lambda c: abs(c[0] - t))
            if abs(ct - t) <= 0.5 * period and (cm.width, cm.height) == (
                camera.width,
                camera.height,
            ):
                color = _rgb(cm)
        T, why = tf.lookup(rep.base_frame, rep.camera_frame, t)
        if T is None:
            problems.append(why)
        else:
            rep.posed += 1
        writer.add(counts, color, T, t)
        rep.frames += 1
    writer.close()
    if problems:
        rep.pose_problem = (
            f"{len(problems)} of {rep.frames} frames have no camera pose: {problems[0]}"
        )
        log.warning("%s: %s", p, rep.pose_problem)
    return rep


def import_recording(
    path: str | Path, out: str | Path, topics: RosTopics | None = None, max_frames: int = 0
) -> Path:
    """`vinetwin import-recording`: a ROS 1 / ROS 2 bag (with its TF poses) or a librealsense
    recording (`capture.realsense`, no poses) as the capture folder `out`."""
    if is_ros_bag(path):
        rep = read_ros_bag(path, out, topics, max_frames)
        log.info(
            "%d frames from %s (%s depth), %d with a camera pose in %s",
            rep.frames, rep.topics["depth"], rep.depth_encoding, rep.posed, rep.base_frame,
        )  # fmt: skip
        return rep.path
    from vinetwin.capture.realsense import read_recording

    return read_recording(path, out, max_frames)
