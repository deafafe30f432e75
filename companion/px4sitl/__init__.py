"""Real PX4 in the loop: PX4 SITL with its built-in simulator (SIH).

* ``launcher``: start one PX4 SITL instance (fresh working folder, free instance, SIH vehicle profile,
  pre-flight wait) and stop it on every way out (end, Ctrl-C, the parent dying);
* ``truth``: the simulator's ground truth (HIL_STATE_QUATERNION on SIH's own link) in local NED;
* ``run``: ``companion sim --autopilot px4`` (one flight of the app against PX4).

``companion eval ... --autopilot px4`` (the paper's studies on PX4, in real time) lives in
companion.evaluation.px4: it uses this package, never the other way round.
"""
