"""Stage 3, regions: where the coach can be trusted, and the critical-state bounds derived from it.

- :mod:`pidlab.region.roa` estimates and certifies the coach's region of attraction (Lyapunov
  level sets checked against MuJoCo simulation);
- :mod:`pidlab.region.bounds` derives the critical-state bounds (a box and/or an ellipsoid) that
  trigger a takeover;
- :mod:`pidlab.region.simulate` holds the simulation helpers both share.
"""
