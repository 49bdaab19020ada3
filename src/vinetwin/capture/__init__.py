"""Captured frames, on disk and live, below both `reconstruct` and `servo`:

- `folder`: the capture folder format (`capture.json`, 16-bit depth and colour PNGs, per-frame
  robot poses and stamps): `read_capture`, `write_capture`, `CaptureWriter`;
- `sources`: every camera source behind one interface (`CameraSource.read()` ->
  `CameraFrame`): a live D405 (`RealSenseSource`), a RealSense recording (`RecordingSource`),
  a capture folder (`FolderSource`); `open_source("realsense" | "bag:F" | "folder:D")`;
- `realsense`: RealSense recordings to capture folders and back, and `SoftwareD405`, a
  pyrealsense2 software device that streams injected frames like a real D405.
"""
