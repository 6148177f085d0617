"""Presentation: console views, figures and the experiment and pipeline reports.

Nothing here computes a result: every function takes what a stage returned and shows it.

- :mod:`pidlab.report.console` prints tables in the terminal;
- :mod:`pidlab.report.plots` draws the coach's analysis and its region (``plot_*(result, ax=None)``);
- :mod:`pidlab.report.curves` draws an experiment's learning curves and measures;
- :mod:`pidlab.report.experiment` writes an experiment's report;
- :mod:`pidlab.report.pipeline` writes the report of ``pidlab run``.
"""
