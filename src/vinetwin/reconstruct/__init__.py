"""Captured frames to a vine mesh (docs/reconstruct.md): `pipeline` (`reconstruct`, what
`vinetwin reconstruct` runs), `synthetic` (synthetic captures of a twin), `sfm` and `odometry`
(poses without a robot), `fusion` (TSDF fusion, clean-up, evaluation). Capture folders and
recordings are read by `vinetwin.capture`."""
