"""pidlab: a MuJoCo model turned into a coached RL agent, with a classical controller as its coach.

The pipeline's stages are plain Python functions first, CLI verbs second:

- :func:`pidlab.plant.model.load_model` resolves a Gymnasium MuJoCo env id or an MJCF file;
- :func:`pidlab.plant.operating_point.resolve_operating_point` picks the point to linearize about;
- :func:`pidlab.linear.linearize.linearize` returns continuous and discrete python-control models;
- :func:`pidlab.linear.lti.analyze_lti` reports eigenvalues, controllability and observability.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("pidlab")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
