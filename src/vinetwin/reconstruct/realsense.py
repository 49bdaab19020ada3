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
from vinetwin.reconstruct.capture import Capture, CaptureError, write_capture


def _rs() -> Any:
    try:
        import pyrealsense2 as rs
    except ImportError as exc:
        raise CaptureError(f"reading RealSense recordings needs pyrealsense2: {exc}") from exc
    return rs


def write_recording(capture: Capture, path: str | Path) -> Path:
    """Writes the capture's frames (depth z16, colour rgb8) as a RealSense recording."""
    rs = _rs()
    path = Path(path)
    if path.exists():
        path.unlink()
    cam = capture.camera
    intr = rs.intrinsics()
    intr.width, intr.height = cam.width, cam.height
    intr.fx, intr.fy, intr.ppx, intr.ppy = cam.fx, cam.fy, cam.cx, cam.cy
    intr.model = rs.distortion.none
    intr.coeffs = [0.0] * 5
    dev = rs.software_device()
    sensor = dev.add_sensor("Stereo Module")
    profiles = []
    for kind, fmt, bpp, uid in (
        (rs.stream.depth, rs.format.z16, 2, 0),
        (rs.stream.color, rs.format.rgb8, 3, 1),
    ):
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid = kind, 0, uid
        vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = cam.width, cam.height, 30, bpp, fmt
        vs.intrinsics = intr
        profiles.append(sensor.add_video_stream(vs))
    ext = rs.extrinsics()
    ext.rotation = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    ext.translation = [0.0, 0.0, 0.0]
    profiles[0].register_extrinsics_to(profiles[1], ext)  # colour registered to depth
    sensor.add_read_only_option(rs.option.depth_units, float(capture.depth_unit))
    recorder = rs.recorder(str(path), dev)
    queue = rs.frame_queue(64)
    sensor.open(profiles)
    sensor.start(queue)

    for i, f in enumerate(capture.frames):
        depth = f.depth_counts()
        color = (
            np.ascontiguousarray(f.color())
            if f.color_path is not None
            else np.zeros((cam.height, cam.width, 3), np.uint8)
        )
        for img, prof, bpp in ((depth, profiles[0], 2), (color, profiles[1], 3)):
            frame = rs.software_video_frame()
            frame.pixels = img
            frame.stride = cam.width * bpp
            frame.bpp = bpp
            frame.timestamp = i * 1000.0 / 30
            frame.domain = rs.timestamp_domain.hardware_clock
            frame.frame_number = i
            frame.profile = prof.as_video_stream_profile()
            sensor.on_video_frame(frame)
        time.sleep(0.01)
    sensor.stop()
    sensor.close()
    del recorder, dev
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
