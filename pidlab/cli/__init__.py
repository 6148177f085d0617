"""The ``pidlab`` command line: one verb per stage, each a thin layer over the Python API.

:mod:`pidlab.cli.main` holds the Typer app; :mod:`pidlab.cli.clidoc` renders its reference page.
"""

from pidlab.cli.main import app, main

__all__ = ["app", "main"]
