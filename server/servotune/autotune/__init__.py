"""Auto-tune assistant (SLAP2, Z1100): identify the plant, propose gains, verify them.

docs/autotune.md explains the method, the rules and their limits. The package:

* ``service``: ``AutoTuner``, the sessions (one per axis) the REST routes drive;
* ``devices.slap2.tuner`` / ``devices.z1100.tuner``: each device's sequence on a live
  axis (``DeviceTuner``);
* ``devices.slap2.gain_rule`` / ``devices.z1100.gain_rule``: the gain searches (pure,
  run in worker threads);
* ``verdict``: whether the tuned run is better than the baseline;
* ``session``, ``context``, ``recording``: API-facing state, hub/bench access, the
  identification recorded as a bench run.

The identification, the models, the controller laws and their simulation are the
shared core in ``servotune.tuning`` (also used by the frequency response and the
what-if view); nothing there imports this package.
"""
