"""RealSense recordings to and from capture folders, through pyrealsense2.

pyrealsense2 2.59 records to rosbag2 files (`.db3`; older librealsense wrote ROS1 `.bag`, which
this same playback path reads when the installed librealsense does). `read_recording` plays a
recording back (not in real time, every frame), aligns colour to depth when both are there, and
writes a capture folder with the depth stream's intrinsics and depth unit; recordings carry no
robot poses. `write_recording` writes a capture's depth (and colour) frames as a recording
through a software device: it serves tests and users without a camera.
"""

from __future__ import annotations

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
    """Plays a RealSense recording back into a capture folder; returns its path."""
    rs = _rs()
    path = Path(path)
    if not path.exists():
        raise CaptureError(f"{path}: no such recording")
    cfg = rs.config()
    cfg.enable_device_from_file(str(path), repeat_playback=False)
    pipe = rs.pipeline()
    try:
        prof = pipe.start(cfg)
    except RuntimeError as exc:
        raise CaptureError(f"{path}: cannot play back: {exc}") from exc
    prof.get_device().as_playback().set_real_time(False)
    streams = {s.stream_type() for s in prof.get_streams()}
    if rs.stream.depth not in streams:
        pipe.stop()
        raise CaptureError(f"{path}: the recording holds no depth stream")
    align = rs.align(rs.stream.depth) if rs.stream.color in streams else None
    frames, camera, unit = [], None, None
    try:
        while True:
            try:
                fs = pipe.wait_for_frames(2000)
            except RuntimeError:
                break  # end of the recording
            if align is not None:
                fs = align.process(fs)
            d = fs.get_depth_frame()
            if not d:
                continue
            if camera is None:
                i = d.profile.as_video_stream_profile().get_intrinsics()
                camera = CameraModel(
                    width=i.width, height=i.height, fx=i.fx, fy=i.fy, cx=i.ppx, cy=i.ppy
                )
                unit = float(d.get_units())
            depth = np.asanyarray(d.get_data()).astype(np.float32) * np.float32(unit)
            c = fs.get_color_frame() if align is not None else None
            color = (
                np.asanyarray(c.get_data()).copy() if c else np.zeros((*depth.shape, 3), np.uint8)
            )
            frames.append((color[..., :3], depth, None))
            if max_frames and len(frames) >= max_frames:
                break
    finally:
        pipe.stop()
    if camera is None or unit is None:
        raise CaptureError(f"{path}: no depth frame could be read")
    return write_capture(
        out, camera, frames, depth_unit=unit, extra={"provenance": {"recording": str(path)}}
    )
