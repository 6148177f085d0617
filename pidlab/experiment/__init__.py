"""Stage 5, experiments: conditions, multi-seed sweeps, and their statistics.

- :mod:`pidlab.experiment.conditions` reads the conditions file (``coach/conditions.toml``);
- :mod:`pidlab.experiment.sweep` plans, runs and resumes a sweep (process pool or Ray);
- :mod:`pidlab.experiment.progress` reads how far a sweep's runs are from their logs;
- :mod:`pidlab.experiment.analysis` reads the runs into per-cell measures;
- :mod:`pidlab.experiment.metrics` computes the measures of one run;
- :mod:`pidlab.experiment.stats` holds the pure statistics (IQM, bootstrap, P(improvement)).
"""
