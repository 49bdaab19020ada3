"""vinetwin: reference-cloud authoring and digital-twin toolkit for robotic vine pruning.

The pipeline stages are subpackages: `twin` (the twin folder, camera, vines), `render`
(synthetic D405 depth and reference clouds), `reconstruct` (frames to a mesh), `servo`
(ICP and PBVS), `web` (the authoring app). The core modules `frames`, `conventions`,
`camera` and `cloud` are shared by all of them. `import vinetwin` stays light: heavy
libraries (open3d, pyrender, mujoco, viser, pycolmap) load only in the modules that use them.
"""

from vinetwin.errors import VinetwinError

__version__ = "0.1.0"
__all__ = ["VinetwinError", "__version__"]
