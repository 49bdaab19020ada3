"""Which topics and frames of a ROS recording to read (`capture.rosbag`): a settings dataclass
with nothing heavy to import, so the command line can nest it."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["RosTopics"]


@dataclass(frozen=True, kw_only=True)
class RosTopics:
    """Which topics and frames to read; empty: the driver's defaults."""

    depth_topic: str = ""
    """ROS bags: the depth image topic (default /camera/depth/image_rect_raw or, ROS 2,
    /camera/camera/depth/image_rect_raw)."""
    info_topic: str = ""
    """ROS bags: its CameraInfo (default: camera_info beside the depth topic)."""
    color_topic: str = ""
    """ROS bags: the colour topic (default .../color/image_rect_raw or image_raw, if present)."""
    base_frame: str = ""
    """ROS bags: the robot base frame (default: the root of the TF tree above the camera)."""
