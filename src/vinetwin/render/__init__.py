"""Synthetic D405 depth and reference clouds.

- `backends`: depth rendering (Open3D ray casting, pyrender, MuJoCo) behind one interface;
- `sensor`: the D405 sensor model (noise, silhouettes, range, quantisation);
- `reference`: one reference cloud (render -> sensor -> the shared perception chain) and its files;
- `export`: batch export of a twin's references, resumable, over worker processes;
- `preview`: a picture of a pose's depth image and reference cloud.

Heavy libraries load only when a backend is created.
"""
