"""Synthetic D405 depth and reference clouds.

- `backends`: depth rendering behind one interface, one module per backend (`raycast`: Open3D
  ray casting; `raster`: vinetwin's compiled rasteriser; `pyrender_gl`; `mujoco_gl`), `auto`'s
  choice and the constructors (`get_backend`, `raycaster`, `scene_backend`);
- `sensor`: the D405 sensor model (noise, silhouettes, range, quantisation);
- `reference`: a pose's reference, owned here (`reference_for`: the exported files with their
  hash check, or render -> sensor -> the shared perception chain) and its files;
- `export`: batch export of a twin's references, resumable, over worker processes; the demo;
- `preview`: a picture of a pose's depth image and reference cloud.

Heavy libraries load only when a backend is created.
"""
