"""Captured frames to a vine mesh (docs/reconstruct.md): `capture` (the capture folder format),
`synthetic` (synthetic captures of a twin), `sfm` (poses from pycolmap), `fusion` (TSDF fusion,
clean-up, evaluation)."""
