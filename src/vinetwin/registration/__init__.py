"""Point-cloud registration, shared by the servo and the reconstruction:

- `icp`: the paper's four ICP variants (point-to-point, LM, point-to-plane, symmetric) behind
  one interface (`ICP(reference, ICPConfig(...)).align(current, T_init)` -> `ICPResult`), built
  once per reference, coarse to fine, with the failure checks a servo needs;
- `_kernels`, `_search_kernels`: their compiled (numba) registration levels, and the
  nearest-neighbour tree and projective index they pair with;
- `search`: the wide search from hypotheses around a prediction;
- `features`: Open3D's FPFH + RANSAC, a proposal for ICP to refine (the servo's arrival, the
  odometry's joining of runs).
"""
