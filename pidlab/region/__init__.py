"""Stage 3, regions: where the coach can be trusted, and the critical-state bounds derived from it.

- :mod:`pidlab.region.roa` estimates and certifies the coach's region of attraction (Lyapunov
  level sets checked against MuJoCo simulation);
- :mod:`pidlab.region.bounds` derives the critical-state bounds (a box and/or an ellipsoid) that
  trigger a takeover;
- :mod:`pidlab.region.rescue` estimates the coach's rescue region by simulation (a lookup grid,
  validated on fresh states), and :mod:`pidlab.region.room` tunes a coach for the largest one;
- :mod:`pidlab.region.takeover` answers, for every shape, whether an observation lies in a spec's
  takeover region (:func:`pidlab.load_region`);
- :mod:`pidlab.region.forecast` asks a rescue region about the box of a forecast's measured
  error (the model predictor, a trigger without a copy of the simulator), bounding a classifier's
  score over a box with :mod:`pidlab.region.relaxation`;
- :mod:`pidlab.region.simulate` holds the simulation helpers they share.
"""
