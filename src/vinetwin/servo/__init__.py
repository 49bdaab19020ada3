"""ICP-based position-based visual servoing.

- `pbvs`: the PBVS error, interaction matrix, control law (constant or adaptive gain, saturation)
  and the kinematic initial guess (paper eqs. 6-8, 11);
- `icp`: the four ICP variants behind one interface (correctness reference; the camera-rate
  speed work, the benchmark and the safety servo step are open work of the servo issue).
"""
