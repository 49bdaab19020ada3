"""Everything simulated, on top of the servo (docs/simulation.md):

- `config`: the settings (`SimConfig`, `Disturbance`, `CampaignConfig`, `ValidateConfig`);
- `robots`, `panda`, `camera`: the simulated arms (a free-flying camera, the MuJoCo Panda)
  and the simulated D405, behind the servo's `Robot` and `CameraSource` interfaces;
- `session`: the one place a simulated run is described and built (`SimSpec`, set up on a
  `SimWorld`; `start_pose`; `servo_session` for `vinetwin servo --camera sim`);
- `simulate`: one closed-loop run through the hardware loop (`simulate(spec, world)` ->
  `SimRun`);
- `workers`: simulation jobs on the executor; `campaign`, `validate`: the paper's campaign and
  per-pose validation, resumable; `report`: their figures and pages; `paper`: the paper's
  tables as data.
"""
