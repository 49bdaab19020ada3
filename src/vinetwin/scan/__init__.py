"""Scans in: a point cloud or mesh of a real plant (LiDAR, stereo, photogrammetry) becomes a
twin with a skeleton and cut candidates (`vinetwin import-scan`). `read` (formats, units),
`clean` (strays, ground, ground clutter, wires, posts), `frame` (the vine frame),
`skeletonize`, `candidates`, `importer` (the pipeline), `report`; `synthetic` (a simulated
scanner) and `evaluate` (accuracy against a known truth) check it."""
