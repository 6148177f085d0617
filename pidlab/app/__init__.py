"""The interactive coach tuner: a Panel app served by ``pidlab tune ENV --ui``.

- :mod:`pidlab.app.live` computes what the views show (no widgets);
- :mod:`pidlab.app.jobs` runs the slow parts (region of attraction, rollouts, auto-tuning,
  bounds) in worker processes with progress and cancellation;
- :mod:`pidlab.app.figures` draws with Bokeh;
- :mod:`pidlab.app.tuner` lays out the widgets and wires the callbacks;
- :mod:`pidlab.app.serve` serves it on a local port.

In a notebook, after ``import panel as pn; pn.extension()``::

    Tuner(load_spec("tuning/InvertedPendulum-v5.pidlab-robust.toml"), "notebook", Path("tuning")).panel()

"""
