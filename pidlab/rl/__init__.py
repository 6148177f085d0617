"""Stage 4, coached training: recipes, the coaching wrapper, evaluation, SB3 training, run folders.

- :mod:`pidlab.rl.recipe` reads the training recipes (``coach/ENV.toml``);
- :mod:`pidlab.rl.schedule` holds the coaching schedules (fading);
- :mod:`pidlab.rl.coaching` is the :class:`gymnasium.Wrapper` in which the coach takes over;
- :mod:`pidlab.rl.evaluation` evaluates the agent alone;
- :mod:`pidlab.rl.train` trains and resumes a run;
- :mod:`pidlab.rl.rundir` writes and reads a run's folder.
"""
