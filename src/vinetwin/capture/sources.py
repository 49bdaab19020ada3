"""Camera sources: where the servo loop gets its depth frames, live or played back, all behind
one interface.

    source = open_source("realsense")              # a D405, live, through pyrealsense2
    source = open_source("bag:run.db3")            # a RealSense recording, at its recorded rate
    source = open_source("folder:capture/")        # a capture folder (vinetwin's frame format)
    frame = source.read(timeout=0.5)               # a CameraFrame, or None: no frame in time
    source.ended                                    # True once a playback has run out

Every source delivers what the D405 streams: 16-bit depth counts and the depth unit (0.1 mm on
the D405), so a simulated, recorded and live frame reach perception through the same
conversion. `CameraFrame.stamp` is in seconds on the clock of `source.now()`, which the loop
uses to refuse stale frames:

- live frames: the host's monotonic clock, from the frame's global/system timestamp (the moment
  of capture) or, for a device clock the host cannot map, the moment of arrival;
- playback: the recording's own timestamps; `now()` advances in real time when the playback is
  paced, and equals the last frame's stamp when it is not (as fast as possible);
- simulation (`servo.sim.SimCameraSource`): simulated time.

Frames played back from a capture folder carry the robot pose recorded with them
(`T_base_camera`), so a recorded run can be replayed without a robot (`--robot none`).
"""

from __future__ import annotations

import math
import queue
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from vinetwin.camera import D405_MIN_DEPTH, CameraModel
from vinetwin.errors import InputError, VinetwinError
from vinetwin.frames import Array

#: D405 depth modes (width, height) the live source accepts (the camera model's list) and its
#: frame rates.
D405_MODES = tuple(D405_MIN_DEPTH)
D405_RATES = (5, 15, 30, 60, 90)


class SourceError(VinetwinError):
    """A camera source cannot start or has failed (no device, unreadable recording)."""


@dataclass
class CameraFrame:
    """One depth frame as the sensor streams it."""

    counts: npt.NDArray[np.uint16]
    """(H, W) depth in counts of `depth_unit`; 0 = no data."""
    depth_unit: float
    """Metres per count."""
    stamp: float
    """Seconds, on the clock of the source's `now()`."""
    number: int
    """The frame's number in its stream."""
    color: npt.NDArray[np.uint8] | None = None
    """(H, W, 3) RGB aligned to depth, when asked for and available."""
    T_base_camera: Array | None = None
    """The robot pose recorded with the frame (capture-folder playback only)."""

    @property
    def depth(self) -> npt.NDArray[np.float32]:
        """z-depth in metres (0 = no data)."""
        from vinetwin import _cloud_kernels

        c = np.ascontiguousarray(self.counts)
        out = np.empty(c.shape, np.float32)
        _cloud_kernels.counts_to_metres(c.reshape(-1), np.float32(self.depth_unit), out.reshape(-1))
        return out


def quantize_depth(depth: Any, depth_unit: float) -> npt.NDArray[np.uint16]:
    """Metres to 16-bit counts as the camera streams them (0 for no data and out of range)."""
    from vinetwin import _cloud_kernels

    d = np.asarray(depth)
    if d.dtype not in (np.float32, np.float64):
        d = d.astype(np.float64)
    if not d.flags.c_contiguous:
        d = d.copy()
    out = np.empty(d.shape, np.uint16)
    _cloud_kernels.quantize_depth(d.reshape(-1), float(depth_unit), out.reshape(-1))
    return out


class CameraSource(ABC):
    """Frames with timestamps and intrinsics. Use as a context manager (closes the device)."""

    camera: CameraModel
    depth_unit: float
    ended: bool = False
    """A playback has delivered its last frame."""
    description: str = ""

    @abstractmethod
    def read(self, timeout: float = 1.0) -> CameraFrame | None:
        """The next frame, or None when none came within `timeout` seconds (or the playback
        ended: see `ended`)."""

    def now(self) -> float:
        """The current time on the clock of the frames' stamps."""
        return time.monotonic()

    def close(self) -> None:  # noqa: B027 - optional for sources that hold nothing
        """Stops the stream and releases the device."""

    def __enter__(self) -> CameraSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ----------------------------------------------------------------------------- capture folder
class FolderSource(CameraSource):
    """Plays a capture folder back (see `reconstruct.capture`), with each frame's recorded robot
    pose. `rate` paces it in real time (frames per second; stamps are then the moments of
    delivery); without it frames come as fast as they are read, stamped with their recorded
    stamps (or frame index / 30 s)."""

    def __init__(self, path: str | Path, rate: float | None = None) -> None:
        from vinetwin.capture.folder import read_capture

        self.capture = read_capture(path, check_frames=False)
        self.camera = self.capture.camera
        self.depth_unit = self.capture.depth_unit
        if rate is not None and not rate > 0:
            raise InputError(f"rate must be positive, got {rate}")
        self.rate = rate
        self.description = f"capture folder {path} ({len(self.capture.frames)} frames)"
        self._i = 0
        self._t0: float | None = None
        self._last = 0.0

    def read(self, timeout: float = 1.0) -> CameraFrame | None:
        frames = self.capture.frames
        if self._i >= len(frames):
            self.ended = True
            return None
        f = frames[self._i]
        counts = f.depth_counts()
        if counts.shape != (self.camera.height, self.camera.width):
            raise SourceError(
                f"frame {f.id}: depth is {counts.shape[1]}x{counts.shape[0]}, the capture's "
                f"camera {self.camera.width}x{self.camera.height}"
            )
        if self.rate is None:
            stamp = f.stamp if f.stamp is not None else self._i / 30.0
        else:
            if self._t0 is None:
                self._t0 = time.monotonic()
            due = self._t0 + self._i / self.rate
            wait = due - time.monotonic()
            if wait > timeout:
                time.sleep(timeout)
                return None
            if wait > 0:
                time.sleep(wait)
            stamp = time.monotonic()
        self._last = stamp
        self._i += 1
        return CameraFrame(counts, self.depth_unit, stamp, self._i - 1, None, f.T_base_camera)

    def now(self) -> float:
        return time.monotonic() if self.rate is not None else self._last


class RosBagSource(FolderSource):
    """Plays a ROS 1 or ROS 2 bag back (`capture.rosbag`): its depth frames, with the camera
    poses its TF recorded, as a capture folder does. The bag is first read into a temporary
    capture folder, removed at `close`."""

    def __init__(self, path: str | Path, rate: float | None = None, topics: Any = None) -> None:
        import tempfile

        from vinetwin.capture.rosbag import read_ros_bag

        self._tmp = tempfile.TemporaryDirectory(prefix="vinetwin-bag-")
        try:
            self.report = read_ros_bag(path, Path(self._tmp.name) / "capture", topics)
            super().__init__(self.report.path, rate)
        except BaseException:
            self._tmp.cleanup()
            raise
        self.description = (
            f"ROS bag {path} ({self.report.frames} frames, {self.report.posed} posed)"
        )

    def close(self) -> None:
        self._tmp.cleanup()


# ----------------------------------------------------------------------------- pyrealsense2
def _rs() -> Any:
    try:
        import pyrealsense2 as rs
    except ImportError as exc:
        raise SourceError(
            f"RealSense cameras and recordings need pyrealsense2 (pip install pyrealsense2): {exc}"
        ) from exc
    return rs


def _host_offset() -> float:
    """time.time() - time.monotonic(): maps wall-clock (epoch) stamps onto the monotonic clock."""
    return time.time() - time.monotonic()


class RealSenseSource(CameraSource):
    """A RealSense depth camera (the D405), live, through pyrealsense2's sensor API: the depth
    stream (z16) at `width` x `height` and `fps`, with colour aligned to depth when `color`.

    `device` is a `pyrealsense2.device` to use (a software device in tests); without it the
    first connected D405 (or the one with serial number `serial`) is opened. `depth_unit` is
    set on the device when the option is writable (the D405 default is 0.1 mm). `camera` is the
    twin's model, whose noise and range facts are kept; the intrinsics come from the stream.
    Frames queue up to `queue_size` deep; the oldest are dropped, so `read` gives recent ones.
    """

    def __init__(
        self,
        width: int = 848,
        height: int = 480,
        fps: int = 30,
        *,
        color: bool = False,
        serial: str | None = None,
        device: Any = None,
        depth_unit: float | None = 1e-4,
        camera: CameraModel | None = None,
        queue_size: int = 2,
    ) -> None:
        rs = _rs()
        self._rs = rs
        if device is None:
            device = self._find_device(serial)
        self.device = device
        name = _info(device, rs.camera_info.name) or "RealSense device"
        sensors = list(device.query_sensors())
        depth_sensor = next((s for s in sensors if _has_stream(s, rs.stream.depth)), None)
        if depth_sensor is None:
            raise SourceError(f"{name}: no depth sensor")
        if depth_unit is not None and depth_sensor.supports(rs.option.depth_units):
            if not depth_sensor.is_option_read_only(rs.option.depth_units):
                depth_sensor.set_option(rs.option.depth_units, depth_unit)
        wanted = [(depth_sensor, rs.stream.depth, rs.format.z16)]
        if color:
            color_sensor = next((s for s in sensors if _has_stream(s, rs.stream.color)), None)
            if color_sensor is None:
                raise SourceError(f"{name}: colour was asked for but the device has none")
            wanted.append((color_sensor, rs.stream.color, rs.format.rgb8))
        opened: dict[int, tuple[Any, list[Any]]] = {}
        depth_profile = None
        for sensor, stream, fmt in wanted:
            prof = _find_profile(sensor, stream, fmt, width, height, fps)
            if prof is None:
                modes = sorted(
                    {
                        f"{p.as_video_stream_profile().width()}x"
                        f"{p.as_video_stream_profile().height()}@{p.fps()}"
                        for p in sensor.get_stream_profiles()
                        if p.stream_type() == stream and p.is_video_stream_profile()
                    }
                )
                raise SourceError(
                    f"{name}: no {stream} stream at {width}x{height} {fps} fps; "
                    f"it offers {', '.join(modes) or 'none'}"
                )
            if stream == rs.stream.depth:
                depth_profile = prof
            opened.setdefault(id(sensor), (sensor, []))[1].append(prof)
        assert depth_profile is not None
        from vinetwin.capture.realsense import intrinsics_camera

        self.camera = intrinsics_camera(depth_profile, camera)
        self.depth_unit = float(f"{depth_sensor.get_option(rs.option.depth_units):.7g}")
        self.fps = fps
        self._align = rs.align(rs.stream.depth) if color else None
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=max(queue_size, 1))
        self._syncer = rs.syncer()
        self._sensors = []
        try:
            for sensor, profiles in opened.values():
                sensor.open(profiles)
                sensor.start(self._syncer)
                self._sensors.append(sensor)
        except RuntimeError as exc:
            self.close()
            raise SourceError(f"{name}: cannot start streaming: {exc}") from exc
        self.description = f"{name} {width}x{height} {fps} fps, depth unit {self.depth_unit} m"

    def _find_device(self, serial: str | None) -> Any:
        rs = self._rs
        devices = list(rs.context().query_devices())
        if not devices:
            raise SourceError("no RealSense camera is connected (is it on a USB 3 port?)")
        for d in devices:
            s = _info(d, rs.camera_info.serial_number)
            n = _info(d, rs.camera_info.name) or ""
            if (serial and s == serial) or (not serial and "D405" in n):
                return d
        found = ", ".join(
            f"{_info(d, rs.camera_info.name)} ({_info(d, rs.camera_info.serial_number)})"
            for d in devices
        )
        want = f"serial {serial}" if serial else "a D405"
        raise SourceError(f"{want} is not connected; found: {found}")

    def read(self, timeout: float = 1.0) -> CameraFrame | None:
        rs = self._rs
        deadline = time.monotonic() + timeout
        while True:  # a set without depth (a lone colour frame) is skipped
            left = deadline - time.monotonic()
            ok, fs = self._syncer.try_wait_for_frames(max(int(left * 1000), 1))
            if not ok:
                return None
            arrival = time.monotonic()
            if self._align is not None and fs.size() > 1:
                try:
                    fs = self._align.process(fs)
                except RuntimeError as exc:
                    raise SourceError(f"aligning colour to depth failed: {exc}") from exc
            d = fs.get_depth_frame()
            if d:
                break
            if left <= 0:
                return None
        counts = np.asanyarray(d.get_data()).copy()
        color = None
        if self._align is not None:
            c = fs.get_color_frame()
            color = np.asanyarray(c.get_data())[..., :3].copy() if c else None
        domain = d.get_frame_timestamp_domain()
        if domain in (rs.timestamp_domain.global_time, rs.timestamp_domain.system_time):
            stamp = d.get_timestamp() / 1000.0 - _host_offset()
            stamp = min(stamp, arrival)  # never in the future
        else:
            stamp = arrival
        return CameraFrame(counts, float(d.get_units()), stamp, int(d.get_frame_number()), color)

    def close(self) -> None:
        for sensor in getattr(self, "_sensors", []):
            try:
                sensor.stop()
                sensor.close()
            except RuntimeError:
                pass
        self._sensors = []


def _info(device: Any, what: Any) -> str | None:
    try:
        return device.get_info(what) if device.supports(what) else None
    except RuntimeError:
        return None


def _has_stream(sensor: Any, stream: Any) -> bool:
    return any(p.stream_type() == stream for p in sensor.get_stream_profiles())


def _find_profile(sensor: Any, stream: Any, fmt: Any, width: int, height: int, fps: int) -> Any:
    for p in sensor.get_stream_profiles():
        if p.stream_type() != stream or p.format() != fmt or p.fps() != fps:
            continue
        if not p.is_video_stream_profile():
            continue
        v = p.as_video_stream_profile()
        if v.width() == width and v.height() == height:
            return p
    return None


class RecordingSource(CameraSource):
    """A RealSense recording (rosbag2 `.db3` as pyrealsense2 2.59 writes it, or a ROS1 `.bag`
    where the installed librealsense reads those), played back through pyrealsense2 with its
    recorded intrinsics and depth unit. `real_time` paces it at the recorded rate (stamps: the
    recording's own, mapped onto the host clock); otherwise every frame is delivered, as fast as
    it is read (stamps: the recording's own) or, with `rate`, at that many frames per second
    (stamps: the moments of delivery)."""

    def __init__(
        self,
        path: str | Path,
        *,
        real_time: bool = True,
        rate: float | None = None,
        color: bool = False,
        camera: CameraModel | None = None,
    ) -> None:
        if rate is not None and not rate > 0:
            raise InputError(f"rate must be positive, got {rate}")
        if rate is not None:
            real_time = False
        self.rate = rate
        self._paced_t0: float | None = None
        self._paced_n = 0
        from vinetwin.capture.realsense import RecordingPlayback, intrinsics_camera

        path = Path(path)

        self._reader = RecordingPlayback(path, real_time=real_time, color=color, error=SourceError)
        self.real_time = real_time
        self.camera = intrinsics_camera(self._reader.depth_profile, camera)
        self._color = color and self._reader.color_profile is not None
        self.depth_unit = math.nan
        self._last = 0.0
        self._offset: float | None = None  # recording stamp -> monotonic, when paced
        self._stopped = False
        self.description = f"recording {path}" + (" (real time)" if real_time else "")
        first = self.read(timeout=5.0)  # the depth unit travels with the frames
        if first is None:
            self.close()
            raise SourceError(f"{path}: no depth frame could be read")
        self._pending: CameraFrame | None = first

    def read(self, timeout: float = 1.0) -> CameraFrame | None:
        pending = getattr(self, "_pending", None)
        if pending is not None:
            self._pending = None
            return pending
        if self._stopped:
            self.ended = True
            return None
        got = self._reader.next(timeout)
        if got is None:
            if self._reader.ended:
                self.ended = True
                self.close()
            return None
        d, c = got
        unit = float(d.get_units())
        if math.isnan(self.depth_unit):
            self.depth_unit = unit
        stamp = d.get_timestamp() / 1000.0
        if self.rate is not None:
            if self._paced_t0 is None:
                self._paced_t0 = time.monotonic()
            wait = self._paced_t0 + self._paced_n / self.rate - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            self._paced_n += 1
            stamp = time.monotonic()
        elif self.real_time:
            if self._offset is None:
                self._offset = time.monotonic() - stamp
            stamp += self._offset
        if stamp <= self._last:  # playback can repeat a stamp; keep the stream's order
            stamp = math.nextafter(self._last, math.inf)
        self._last = stamp
        counts = np.asanyarray(d.get_data()).copy()
        color = np.asanyarray(c.get_data())[..., :3].copy() if self._color and c else None
        return CameraFrame(counts, unit, stamp, int(d.get_frame_number()), color)

    def now(self) -> float:
        return time.monotonic() if self.real_time or self.rate is not None else self._last

    def close(self) -> None:
        if not self._stopped:
            self._stopped = True
            self._reader.close()


# ----------------------------------------------------------------------------- by name
CAMERAS = ("realsense", "bag:PATH", "folder:PATH", "sim")


def open_source(
    spec: str,
    *,
    camera: CameraModel | None = None,
    width: int = 848,
    height: int = 480,
    fps: int = 30,
    color: bool = False,
    rate: float | None = None,
    serial: str | None = None,
) -> CameraSource:
    """A source from its command-line name: `realsense` (live D405), `bag:PATH` (a ROS 1 or
    ROS 2 bag with a depth image topic, replayed with its TF poses like a capture folder; or a
    librealsense recording: at its recorded rate by default, as fast as read with `rate` 0, at `rate` frames per second
    otherwise), `folder:PATH` (a capture folder: as fast as read, or at `rate`). `sim` is built
    by the simulation (`servo.sim`)."""
    kind, _, arg = spec.partition(":")
    if kind == "realsense":
        if (width, height) not in D405_MODES or fps not in D405_RATES:
            raise InputError(
                f"the D405 streams depth at {', '.join(f'{w}x{h}' for w, h in D405_MODES)}"
                f" and {', '.join(map(str, D405_RATES))} fps; got {width}x{height} {fps} fps"
            )
        return RealSenseSource(
            width, height, fps, color=color, serial=serial or (arg or None), camera=camera
        )
    if kind == "bag" and arg:
        from vinetwin.capture.rosbag import is_ros_bag

        if is_ros_bag(arg):  # a ROS 1 / ROS 2 bag; else a librealsense recording
            return RosBagSource(arg, rate=rate or None)
        return RecordingSource(
            arg, real_time=rate is None, rate=rate or None, color=color, camera=camera
        )
    if kind == "folder" and arg:
        return FolderSource(arg, rate=rate or None)
    raise InputError(f"unknown camera '{spec}'; choose one of: {', '.join(CAMERAS)}")
