"""Stage 2, the coach: its spec, its discrete PID law, its analysis and its automatic tuning.

- :mod:`pidlab.controller.spec` reads, validates and writes coach specs (``tuning/*.toml``);
- :mod:`pidlab.controller.pid` is the one discrete control law every other stage runs;
- :mod:`pidlab.controller.analysis` computes margins, closed-loop poles and responses;
- :mod:`pidlab.controller.autotune` tunes a coach from a per-env template;
- :mod:`pidlab.controller.rollout` runs the coach alone on the real env;
- :mod:`pidlab.controller.animation` renders such a rollout.
"""
