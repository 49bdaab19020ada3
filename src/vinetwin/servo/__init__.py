"""ICP-based position-based visual servoing (see docs/servo.md).

- `icp`: the four ICP variants behind one interface, compiled (numba), built once per reference;
- `pbvs`: the PBVS error, interaction matrix, control law (constant or adaptive gain, saturation)
  and the kinematic initial guess (paper eqs. 6-8, 11);
- `step`: `Servo`, one call per frame from a cloud or depth image to a camera twist, with the
  safety rules that command zero velocity when the alignment is not trusted.
"""
