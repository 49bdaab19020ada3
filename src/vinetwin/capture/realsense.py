"""RealSense recordings to and from capture folders, through pyrealsense2.

pyrealsense2 2.59 records to rosbag2 files (`.db3`; older librealsense wrote ROS1 `.bag`, which
this same playback path reads when the installed librealsense does). `read_recording` plays a
recording back (not in real time, every frame), aligns colour to depth when both are there, and
writes a capture folder with the depth stream's intrinsics and depth unit; recordings carry no
robot poses. `write_recording` writes a capture's depth (and colour) frames as a recording
through a software device: it serves tests and users without a camera.
"""

from __future__ import annotations

import queue
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from vinetwin.camera import CameraModel
from vinetwin.capture.folder import Capture, CaptureError, write_capture


def _rs() -> Any:
    try:
        import pyrealsense2 as rs
    except ImportError as exc:
        raise CaptureError(f"reading RealSense recordings needs pyrealsense2: {exc}") from exc
    return rs


class SoftwareD405:
    """A pyrealsense2 software device that presents a D405's depth (z16) and colour (rgb8)
    streams at the camera's size and `fps`, with the camera's intrinsics and depth unit; frames
    are pushed in with `inject`. It lets the live-camera and recording code run through the real
    library without a camera (tests, demos). `recorder(path)` records what is injected."""

    def __init__(self, camera: CameraModel, fps: int = 30, depth_unit: float = 1e-4) -> None:
        rs = _rs()
        self._rs = rs
        self.camera = camera
        self.fps = fps
        intr = rs.intrinsics()
        intr.width, intr.height = camera.width, camera.height
        intr.fx, intr.fy, intr.ppx, intr.ppy = camera.fx, camera.fy, camera.cx, camera.cy
        intr.model = rs.distortion.none
        intr.coeffs = [0.0] * 5
        self.device = rs.software_device()
        self.device.register_info(rs.camera_info.name, "Intel RealSense D405 (software)")
        self.device.register_info(rs.camera_info.serial_number, "000000000405")
        self.sensor = self.device.add_sensor("Stereo Module")
        self.profiles = []
        for kind, fmt, bpp, uid in (
            (rs.stream.depth, rs.format.z16, 2, 0),
            (rs.stream.color, rs.format.rgb8, 3, 1),
        ):
            vs = rs.video_stream()
            vs.type, vs.index, vs.uid = kind, 0, uid
            vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = camera.width, camera.height, fps, bpp, fmt
            vs.intrinsics = intr
            self.profiles.append(self.sensor.add_video_stream(vs))
        ext = rs.extrinsics()
        ext.rotation = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        ext.translation = [0.0, 0.0, 0.0]
        self.profiles[0].register_extrinsics_to(self.profiles[1], ext)  # colour registered
        self.sensor.add_read_only_option(rs.option.depth_units, float(depth_unit))
        self.device.create_matcher(rs.matchers.dlr_c)  # depth and colour paired, as a D400's
        self.number = 0

    def recorder(self, path: str | Path) -> Any:
        """Records every frame injected from now on (keep the returned object alive)."""
        return self._rs.recorder(str(path), self.device)

    def inject(
        self,
        counts: np.ndarray,
        color: np.ndarray | None = None,
        stamp_ms: float | None = None,
        domain: str = "system_time",
    ) -> None:
        """Pushes one frame: depth counts (uint16 HxW), optional colour (uint8 HxWx3), its
        timestamp in ms (default: now, on the host's clock) in the given timestamp domain."""
        rs = self._rs
        stamp = time.time() * 1000.0 if stamp_ms is None else stamp_ms
        images: list[tuple[np.ndarray, Any, int]] = [
            (np.ascontiguousarray(counts, dtype=np.uint16), self.profiles[0], 2)
        ]
        if color is not None:
            images.append((np.ascontiguousarray(color, dtype=np.uint8), self.profiles[1], 3))
        for img, prof, bpp in images:
            frame = rs.software_video_frame()
            frame.pixels = img
            frame.stride = self.camera.width * bpp
            frame.bpp = bpp
            frame.timestamp = stamp
            frame.domain = getattr(rs.timestamp_domain, domain)
            frame.frame_number = self.number
            frame.profile = prof.as_video_stream_profile()
            self.sensor.on_video_frame(frame)
        self.number += 1


def intrinsics_camera(profile: Any, base: CameraModel | None) -> CameraModel:
    """A camera model with a pyrealsense2 stream profile's size and intrinsics, the rest (noise,
    range, depth unit) from `base` (defaults without it)."""
    i = profile.as_video_stream_profile().get_intrinsics()
    fields = {} if base is None else base.to_dict()
    fields.update(width=i.width, height=i.height, fx=i.fx, fy=i.fy, cx=i.ppx, cy=i.ppy)
    return CameraModel.from_dict(fields)


END_GRACE_S = 0.25
"""After the playback device reports the file's end, how long `RecordingPlayback.next` still
waits for frames its callbacks are handing over before it calls the end."""


class RecordingPlayback:
    """The depth frames of a RealSense recording, in the file's order, each with its colour
    frame (same stamp) when `color` and the recording has colour. Read from the playback
    device's own sensors, not `rs.pipeline`: the pipeline, started and then switched out of real
    time, dropped the second frame in 8 of 20 playbacks of a 15-frame recording (librealsense
    2.59), and its maintainers point to the sensors for drop-free reading.

    Not `real_time`: the file is read as fast as `next` takes frames, and none is dropped (the
    reader waits for the consumer; at most `queue_size` frames are held). `real_time`:
    librealsense paces the frames at their recorded stamps; a consumer that falls behind gets
    the newest ones (the oldest are dropped), as from a live camera. `next` gives pyrealsense2
    frames, valid until `close`, colour aligned to depth (the pair made a frameset for
    `rs.align` by a processing block). Errors are raised as `error`."""

    def __init__(
        self,
        path: str | Path,
        *,
        real_time: bool,
        color: bool = False,
        queue_size: int = 4,
        error: type[Exception] = CaptureError,
    ) -> None:
        rs = _rs()
        self._rs = rs
        self.path = Path(path)
        if not self.path.exists():
            raise error(f"{self.path}: no such recording")
        self.real_time = real_time
        self._queue: queue.Queue[tuple[Any, Any]] = queue.Queue(maxsize=max(queue_size, 1))
        self._lock = threading.Lock()
        self._closing = threading.Event()
        self._stopped = threading.Event()
        self._depth: Any = None  # a depth frame waiting for its colour
        self._color: Any = None  # a colour frame waiting for its depth
        self._pairing: list[Any] = []
        self._end_seen: float | None = None  # when the playback was first seen stopped
        self._ended = False
        try:
            self._device = rs.context().load_device(str(self.path))
            self._playback = self._device.as_playback()
            self._playback.set_real_time(real_time)
        except RuntimeError as exc:
            raise error(f"{self.path}: cannot play back: {exc}") from exc
        self.depth_profile: Any = None
        self.color_profile: Any = None
        chosen: list[tuple[Any, list[Any]]] = []
        for sensor in self._device.query_sensors():
            mine = []
            for p in sensor.get_stream_profiles():
                if p.stream_type() == rs.stream.depth and self.depth_profile is None:
                    self.depth_profile = p
                    mine.append(p)
                elif color and p.stream_type() == rs.stream.color and self.color_profile is None:
                    self.color_profile = p
                    mine.append(p)
            if mine:
                chosen.append((sensor, mine))
        if self.depth_profile is None:
            raise error(f"{self.path}: the recording holds no depth stream")
        self._align = rs.align(rs.stream.depth) if self.color_profile is not None else None
        self._composer = rs.processing_block(self._compose)
        self._composed: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._composer.start(self._keep_composed)
        self._playback.set_status_changed_callback(self._on_status)
        self._sensors: list[Any] = []
        try:
            for sensor, profiles in chosen:
                sensor.open(profiles)
                self._sensors.append(sensor)
                sensor.start(self._on_frame)
        except RuntimeError as exc:
            self.close()
            raise error(f"{self.path}: cannot play back: {exc}") from exc

    # librealsense's threads
    def _on_status(self, status: Any) -> None:
        if status == self._rs.playback_status.stopped:
            self._stopped.set()

    def _hand_over(self, item: tuple[Any, Any]) -> None:
        if self.real_time:  # a live camera's behaviour: keep the newest
            while True:
                try:
                    self._queue.put_nowait(item)
                    return
                except queue.Full:
                    try:
                        self._queue.get_nowait()
                    except queue.Empty:
                        pass
        while not self._closing.is_set():  # every frame: wait for the consumer
            try:
                self._queue.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def _on_frame(self, frame: Any) -> None:
        rs = self._rs
        frames = list(frame.as_frameset()) if frame.is_frameset() else [frame]
        for f in frames:
            f.keep()
            kind = f.get_profile().stream_type()
            ready: list[tuple[Any, Any]] = []
            with self._lock:
                if kind == rs.stream.depth:
                    if self.color_profile is None:
                        ready.append((f, None))
                    else:
                        if self._depth is not None:  # the last depth had no colour
                            ready.append((self._depth, None))
                        self._depth = f
                elif kind == rs.stream.color:
                    self._color = f
                if self._depth is not None and self._color is not None:
                    if abs(self._depth.get_timestamp() - self._color.get_timestamp()) < 1.0:
                        ready.append((self._depth, self._color))
                        self._depth = self._color = None
            for item in ready:
                self._hand_over(item)

    def _compose(self, frame: Any, source: Any) -> None:
        source.frame_ready(source.allocate_composite_frame(self._pairing))

    def _keep_composed(self, frame: Any) -> None:
        frame.keep()
        self._composed.put(frame)

    # the consumer's thread
    @property
    def ended(self) -> bool:
        """The whole recording has been delivered (`next` said so)."""
        return self._ended

    def next(self, timeout: float = 1.0) -> tuple[Any, Any] | None:
        """The next (depth, colour or None) frames, aligned; None after `timeout` seconds
        without one, or at the end (`ended`)."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                depth, color = self._queue.get(timeout=min(0.05, max(timeout, 0.001)))
                break
            except queue.Empty:
                now = time.monotonic()
                if self._stopped.is_set():
                    # the file's end: frames still being handed over by the callbacks' threads
                    # get a moment before the end is called
                    if self._end_seen is None:
                        self._end_seen = now
                    if now - self._end_seen < END_GRACE_S:
                        continue
                    with self._lock:  # a last depth frame whose colour never came
                        depth, self._depth = self._depth, None
                    if depth is not None:
                        color = None
                        break
                    if self._queue.empty():
                        self._ended = True
                        return None
                    continue
                if now >= deadline:
                    return None
        if color is not None and self._align is not None:
            self._pairing = [depth, color]
            self._composer.invoke(depth)
            fs = self._align.process(self._composed.get(timeout=5.0).as_frameset())
            fs.keep()
            depth, color = fs.get_depth_frame(), fs.get_color_frame()
        return depth.as_depth_frame(), color

    def close(self) -> None:
        self._closing.set()
        for sensor in self._sensors:
            try:
                sensor.stop()
            except RuntimeError:
                pass
            try:
                sensor.close()
            except RuntimeError:
                pass
        self._sensors = []


def write_recording(capture: Capture, path: str | Path) -> Path:
    """Writes the capture's frames (depth z16, colour rgb8) as a RealSense recording."""
    path = Path(path)
    if path.exists():
        path.unlink()
    cam = capture.camera
    soft = SoftwareD405(cam, fps=30, depth_unit=capture.depth_unit)
    recorder = soft.recorder(path)
    queue = soft._rs.frame_queue(64)
    soft.sensor.open(soft.profiles)
    soft.sensor.start(queue)
    for i, f in enumerate(capture.frames):
        color = (
            np.ascontiguousarray(f.color())
            if f.color_path is not None
            else np.zeros((cam.height, cam.width, 3), np.uint8)
        )
        soft.inject(f.depth_counts(), color, stamp_ms=i * 1000.0 / 30, domain="hardware_clock")
        time.sleep(0.01)
    soft.sensor.stop()
    soft.sensor.close()
    del recorder, soft
    if not path.exists():
        raise CaptureError(f"{path}: the recorder wrote nothing")
    return path


def read_recording(path: str | Path, out: str | Path, max_frames: int = 0) -> Path:
    """Plays a RealSense recording back into a capture folder (every frame, in order, colour
    aligned to depth when recorded); returns its path."""
    reader = RecordingPlayback(path, real_time=False, color=True)
    camera = intrinsics_camera(reader.depth_profile, None)
    frames, unit = [], None
    try:
        while (got := reader.next(timeout=5.0)) is not None:
            d, c = got
            if unit is None:
                unit = float(d.get_units())
            depth = np.asanyarray(d.get_data()).astype(np.float32) * np.float32(unit)
            color = (
                np.asanyarray(c.get_data())[..., :3].copy()
                if c
                else np.zeros((*depth.shape, 3), np.uint8)
            )
            frames.append((color, depth, None))
            if max_frames and len(frames) >= max_frames:
                break
    finally:
        reader.close()
    if unit is None:
        raise CaptureError(f"{path}: no depth frame could be read")
    return write_capture(
        out, camera, frames, depth_unit=unit, extra={"provenance": {"recording": str(path)}}
    )
