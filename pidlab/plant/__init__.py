"""Stage 0, the plant: a MuJoCo model, its model card, its observation and its operating point.

- :mod:`pidlab.plant.model` loads a Gymnasium MuJoCo env id or an MJCF file;
- :mod:`pidlab.plant.card` reads the model cards in ``models/`` (named states, termination limits,
  per-env facts);
- :mod:`pidlab.plant.observation` maps the env's observation vector to named signals and back;
- :mod:`pidlab.plant.operating_point` resolves and settles the point to linearize about.
"""
