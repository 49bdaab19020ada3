"""vinetwin: reference-cloud authoring and digital-twin toolkit for robotic vine pruning.

The pipeline stages are subpackages (docs/architecture.md): `twin` (the twin folder, pruning
poses, vines), `capture` (frames and camera sources), `registration` (ICP and the wide search),
`render` (synthetic D405 depth and a pose's reference cloud), `reconstruct` (frames to a mesh),
`servo` (PBVS, the loop, the robot, a servo session), `sim` (the simulated session, campaigns,
validation) and `web` (the authoring app). The core modules `frames`, `conventions`, `camera`
and `cloud` are shared by all of them. `import vinetwin` stays light: heavy
libraries (open3d, pyrender, mujoco, viser, pycolmap) load only in the modules that use them.
"""

import os

#: Spins of an idle OpenMP (libgomp) thread before it sleeps; libgomp's default is 300000.
#: numba's parallel kernels (the ICP's) run on libgomp, whose threads spin a few milliseconds
#: after each parallel region: on a 2-core machine the next frame's perception threads, which
#: follow the ICP's last region in a back-to-back servo loop, then waited for a core (the dense
#: vine's 2 mm perception 7-9 ms instead of 5-6). 10000 still keeps them awake between the
#: ICP's own regions (its time unchanged). libgomp reads it when it loads (numba's at its first
#: parallel kernel), so it is set on the package's import; a value already in the environment
#: wins. `benchmarks/icp.py` loads small_gicp (its own libgomp) without it.
GOMP_SPINCOUNT = "10000"
os.environ.setdefault("GOMP_SPINCOUNT", GOMP_SPINCOUNT)

#: numba's threading layers in the order tried: OpenMP (libgomp, shared with Open3D), then the
#: workqueue, which needs nothing installed. TBB comes last: where one is installed it is often
#: older than numba accepts, and numba then warns on every first parallel call (the web demo's
#: log showed "The TBB threading layer requires TBB version 2021 update 6 or later").
NUMBA_THREADING_LAYERS = ("omp", "workqueue", "tbb")
os.environ.setdefault("NUMBA_THREADING_LAYER_PRIORITY", " ".join(NUMBA_THREADING_LAYERS))

from vinetwin.errors import VinetwinError  # noqa: E402

__version__ = "0.1.0"
__all__ = ["VinetwinError", "__version__"]
