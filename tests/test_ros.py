"""ROS 1 and ROS 2 recordings, written here with rosbags as the RealSense ROS driver records them
(millimetre depth, CameraInfo, /tf from panda_link0 to camera_depth_optical_frame), read into
capture folders bit-exact, reconstructed and replayed by the servo; servo runs written as MCAP."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import VineViews
from vinetwin import frames as fr
from vinetwin.capture.folder import read_capture
from vinetwin.capture.rosbag import RosTopics, is_ros_bag, read_ros_bag

rosbags = pytest.importorskip("rosbags")
from rosbags.typesys import Stores, get_typestore  # noqa: E402

BASE, FLANGE, CAMERA = "panda_link0", "panda_link8", "camera_depth_optical_frame"
T_FLANGE_CAMERA = fr.make_pose(fr.so3_exp([0.0, 0.0, 0.1]), [0.05, 0.0, 0.04])


def _quat_xyzw(R: np.ndarray) -> tuple[float, float, float, float]:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return float(x), float(y), float(z), float(w)


class _Msgs:
    """Message builders for one ROS distribution's typestore."""

    def __init__(self, ros1: bool) -> None:
        self.ros1 = ros1
        self.ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
        if "tf2_msgs/msg/TFMessage" not in self.ts.types:  # not in rosbags' noetic store
            from rosbags.typesys import get_types_from_msg

            self.ts.register(
                get_types_from_msg(
                    "geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"
                )
            )
        self.T = self.ts.types

    def header(self, t: float, frame: str):  # type: ignore[no-untyped-def]
        ns = round(t * 1e9)
        stamp = self.T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        if self.ros1:
            return self.T["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
        return self.T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def image(self, t: float, mm: np.ndarray, metres: bool = False):  # type: ignore[no-untyped-def]
        h, w = mm.shape
        if metres:  # 32FC1, no data as NaN
            m = np.where(mm > 0, mm / 1000.0, np.nan).astype("<f4")
            data, enc, step = np.frombuffer(m.tobytes(), np.uint8), "32FC1", 4 * w
        else:
            data, enc, step = np.frombuffer(mm.astype("<u2").tobytes(), np.uint8), "16UC1", 2 * w
        return self.T["sensor_msgs/msg/Image"](
            header=self.header(t, CAMERA), height=h, width=w, encoding=enc,
            is_bigendian=0, step=step, data=data,
        )  # fmt: skip

    def info(self, t: float, cam):  # type: ignore[no-untyped-def]
        K = np.array([cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1], float)
        P = np.array([cam.fx, 0, cam.cx, 0, 0, cam.fy, cam.cy, 0, 0, 0, 1, 0], float)
        roi = self.T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        names = ("D", "K", "R", "P") if self.ros1 else ("d", "k", "r", "p")
        return self.T["sensor_msgs/msg/CameraInfo"](
            header=self.header(t, CAMERA), height=cam.height, width=cam.width,
            distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi,
            **dict(zip(names, (np.zeros(5), K, np.eye(3).ravel(), P), strict=True)),
        )  # fmt: skip

    def tf(self, t: float, parent: str, child: str, T: np.ndarray):  # type: ignore[no-untyped-def]
        x, y, z, w = _quat_xyzw(T[:3, :3])
        tr = self.T["geometry_msgs/msg/Transform"](
            translation=self.T["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
            rotation=self.T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w),
        )
        st = self.T["geometry_msgs/msg/TransformStamped"](
            header=self.header(t, parent), child_frame_id=child, transform=tr
        )
        return self.T["tf2_msgs/msg/TFMessage"](transforms=[st])

    def serialize(self, msg) -> bytes:  # type: ignore[no-untyped-def]
        if self.ros1:
            return bytes(self.ts.serialize_ros1(msg, msg.__msgtype__))
        return bytes(self.ts.serialize_cdr(msg, msg.__msgtype__))


def write_bag(path: Path, ros1: bool, frames: list[tuple[float, np.ndarray, np.ndarray]], cam,  # type: ignore[no-untyped-def]
              connect_tf: bool = True, metres: bool = False) -> Path:  # fmt: skip
    """A bag as the RealSense ROS driver (plus robot_state_publisher) records it: depth in mm
    and its CameraInfo per frame, the arm's moving flange on /tf at 4x the frame rate (its
    stamps not those of the images: interpolated), the hand-eye transform on /tf_static."""
    m = _Msgs(ros1)
    ns = "/camera" if ros1 else "/camera/camera"
    if ros1:
        from rosbags.rosbag1 import Writer

        w = Writer(path)
    else:
        from rosbags.rosbag2 import Writer

        w = Writer(path, version=9)
    with w:
        c_img = w.add_connection(
            f"{ns}/depth/image_rect_raw", "sensor_msgs/msg/Image", typestore=m.ts
        )
        c_info = w.add_connection(
            f"{ns}/depth/camera_info", "sensor_msgs/msg/CameraInfo", typestore=m.ts
        )
        c_tf = w.add_connection("/tf", "tf2_msgs/msg/TFMessage", typestore=m.ts)
        c_static = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=m.ts)
        t0 = frames[0][0]
        T_fc = T_FLANGE_CAMERA
        static = m.tf(t0, FLANGE, CAMERA if connect_tf else "elsewhere", T_fc)
        w.write(c_static, int(t0 * 1e9), m.serialize(static))
        # the flange moves at constant velocity (`flange_at`), sampled at 4x the frame rate
        # off the image stamps (the importer interpolates), and at both ends
        times = [f[0] for f in frames]
        dt = (times[1] - times[0]) / 4
        samples = [times[0] + k * dt + 1e-3 for k in range(4 * (len(frames) - 1))]
        for t in [times[0], *samples, times[-1]]:
            msg = m.tf(t, BASE, FLANGE, flange_at(t, frames))
            w.write(c_tf, int(t * 1e9), m.serialize(msg))
        for t, mm, _T in frames:
            w.write(c_info, int(t * 1e9), m.serialize(m.info(t, cam)))
            w.write(c_img, int(t * 1e9), m.serialize(m.image(t, mm, metres)))
    return path


T0 = 100.0
RATE = 10.0
VELOCITY = np.array([0.1, 0.0, 0.02])  # m/s of the flange, in the base (= vine) frame


def flange_at(t: float, frames: list) -> np.ndarray:  # type: ignore[type-arg]
    """The flange's pose at time t: a straight line at constant velocity, no rotation."""
    F0 = frames[0][2] @ fr.invert(T_FLANGE_CAMERA)
    return fr.make_pose(F0[:3, :3], F0[:3, 3] + VELOCITY * (t - T0))


def _frames(vine_views: VineViews, n: int = 6) -> list[tuple[float, np.ndarray, np.ndarray]]:
    """Depth in mm (0 = no data) of the sample vine seen from a camera on a flange moving in a
    straight line, at 10 Hz: (stamp, depth, T_base_camera)."""
    twin = vine_views.twin
    goal = twin.poses[0].T_vine_camera
    out = []
    for k in range(n):
        t = T0 + k / RATE
        T = fr.make_pose(goal[:3, :3], goal[:3, 3] + VELOCITY * (t - T0))
        d = vine_views.depth(T, seed=k)
        mm = np.where(np.isfinite(d) & (d > 0), np.round(d * 1000), 0).astype(np.uint16)
        out.append((t, mm, T))
    return out


def _rel_poses(T_list: list[np.ndarray]) -> list[np.ndarray]:
    return [fr.invert(T_list[0]) @ T for T in T_list]


@pytest.mark.parametrize("ros1", [True, False], ids=["ros1", "ros2"])
def test_a_driver_recording_imports_bit_exact_with_tf_poses(
    vine_views: VineViews, tmp_path: Path, ros1: bool
) -> None:
    cam = vine_views.twin.camera
    frames = _frames(vine_views)
    bag = write_bag(tmp_path / ("rec.bag" if ros1 else "rec2"), ros1, frames, cam)
    assert is_ros_bag(bag)
    rep = read_ros_bag(bag, tmp_path / "cap")
    assert rep.frames == len(frames) and rep.posed == len(frames) and not rep.pose_problem
    assert rep.base_frame == BASE and rep.camera_frame == CAMERA
    cap = read_capture(tmp_path / "cap")
    assert cap.depth_unit == 0.001
    assert (cap.camera.fx, cap.camera.cx, cap.camera.width) == (cam.fx, cam.cx, cam.width)
    for f, (t, mm, T) in zip(cap.frames, frames, strict=True):
        np.testing.assert_array_equal(f.depth_counts(), mm)  # bit-exact, no-data stays 0
        assert f.stamp == pytest.approx(t, abs=1e-9)
        # the TF chain gives the flange path times the hand-eye: the camera pose up to the
        # base's placement, which is the identity here
        assert f.T_base_camera is not None
        assert fr.pose_error(f.T_base_camera, T)[0] < 1e-6
        assert fr.pose_error(f.T_base_camera, T)[1] < 1e-6


def test_a_recording_without_a_tf_chain_imports_without_poses(
    vine_views: VineViews, tmp_path: Path
) -> None:
    frames = _frames(vine_views, 3)
    bag = write_bag(tmp_path / "rec.bag", True, frames, vine_views.twin.camera, connect_tf=False)
    rep = read_ros_bag(bag, tmp_path / "cap", RosTopics(base_frame=BASE))
    assert rep.frames == 3 and rep.posed == 0
    assert "does not connect" in rep.pose_problem
    assert all(f.T_base_camera is None for f in read_capture(tmp_path / "cap").frames)


@pytest.mark.parametrize("ros1", [True, False], ids=["ros1", "ros2"])
def test_cli_imports_reconstructs_and_replays_a_bag(
    vine_views: VineViews, tmp_path: Path, ros1: bool
) -> None:
    import shutil

    from vinetwin.cli import main
    from vinetwin.servo.loop import read_log

    cam = vine_views.twin.camera
    frames = _frames(vine_views, 8)
    bag = write_bag(tmp_path / ("rec.bag" if ros1 else "rec2"), ros1, frames, cam)
    assert main(["import-recording", str(bag), "--out", str(tmp_path / "cap")]) == 0
    assert main(["reconstruct", str(tmp_path / "cap"), "--twin", str(tmp_path / "r.twin")]) == 0
    twin_dir = tmp_path / "t.twin"
    shutil.copytree(vine_views.twin.root, twin_dir, ignore=shutil.ignore_patterns("references"))
    log = tmp_path / "replay.jsonl"
    args = ["servo", "--twin", str(twin_dir), "--camera", f"bag:{bag}", "--robot", "none",
            "--dry-run", "--duration", "0", "--log", str(log)]  # fmt: skip
    assert main(args) == 0
    _, cycles, summary = read_log(log)
    assert len(cycles) == len(frames)
    assert all(c["T_base_camera"] is not None for c in cycles)  # the recorded TF poses
    assert summary["trusted"] >= len(frames) - 2
    assert not any(any(c["sent"]) for c in cycles)
    assert math.isfinite(cycles[0]["cycle_ms"])


def test_a_servo_run_written_as_mcap_reads_back_with_its_topics(
    vine_views: VineViews, tmp_path: Path
) -> None:
    import shutil
    from collections import Counter

    from mcap.reader import make_reader

    from vinetwin.cli import main
    from vinetwin.servo.loop import read_log
    from vinetwin.servo.mcap_log import TOPICS

    twin_dir = tmp_path / "t.twin"
    shutil.copytree(vine_views.twin.root, twin_dir, ignore=shutil.ignore_patterns("references"))
    args = ["servo", "--twin", str(twin_dir), "--duration", "1.0", "--log", str(tmp_path / "s.jsonl"),
            "--mcap", str(tmp_path / "run")]  # fmt: skip
    assert main(args) == 0
    _, cycles, _ = read_log(tmp_path / "s.jsonl")
    files = list((tmp_path / "run").glob("*.mcap"))
    assert len(files) == 1
    with files[0].open("rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None
        schemas = {ch.topic: summary.schemas[ch.schema_id].name for ch in summary.channels.values()}
        counts = Counter(ch.topic for _, ch, _ in reader.iter_messages())
    assert schemas == TOPICS
    n = len(cycles)
    assert counts == {
        "/tf_static": 1, "/vinetwin/reference_cloud": 1, "/tf": n, "/vinetwin/live_cloud": n,
        "/vinetwin/twist": n, "/vinetwin/trust": n,
    }  # fmt: skip


def test_metre_depth_is_stored_in_tenth_millimetres(vine_views: VineViews, tmp_path: Path) -> None:
    frames = _frames(vine_views, 3)
    bag = write_bag(tmp_path / "rec2", False, frames, vine_views.twin.camera, metres=True)
    rep = read_ros_bag(bag, tmp_path / "cap")
    assert rep.depth_encoding == "32FC1"
    cap = read_capture(tmp_path / "cap")
    assert cap.depth_unit == 1e-4
    for f, (_t, mm, _T) in zip(cap.frames, frames, strict=True):
        np.testing.assert_array_equal(f.depth_counts(), mm.astype(np.uint32) * 10)  # NaN -> 0
