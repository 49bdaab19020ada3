"""Captured frames to a vine mesh (docs/reconstruct.md): `capture` (the capture folder format),
`realsense` (recordings), `synthetic` (synthetic captures of a twin), `sfm` and `odometry`
(poses without a robot), `fusion` (TSDF fusion, clean-up, evaluation)."""
