"""ICP-based position-based visual servoing, the controller only (docs/servo.md, hardware.md):

- `config`: every servo setting, declared once (`Limits`, `CommandLimits`, `SafetyConfig`,
  `ServoConfig`, `LoopConfig`, `ArrivalConfig`, `RunnerConfig`, `CheckConfig`, the envelope);
- `pbvs`: the PBVS error, interaction matrix, control law and kinematic guess (eqs. 6-8, 11);
- `step`: `Servo`, one call per frame from a depth image to a camera twist, with the trust
  rules that command zero velocity when the alignment is not trusted; `make_servo`;
- `loop`: `run_loop`, the one loop for simulation and hardware, and its cycle log;
- `robot`: the robot interface with its command guard and watchdog, and the Franka adapter;
- `rendered_camera`: a D405 rendered from the twin at a robot's pose (the simulator's camera
  and a stand-in camera for bringing up a robot link);
- `session`: a servo session (`Session`), the hardware one (`hardware_session`) and the
  arrival registration both kinds start with (`arrive`);
- `runner`: `vinetwin servo` (`run_pose`), the command only;
- `arrival`, `check`, `mcap_log`: the arrival registration, `vinetwin check-reference`, the run as
  MCAP.
"""
