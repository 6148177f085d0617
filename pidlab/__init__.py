"""pidlab: a MuJoCo model turned into a coached RL agent, with a classical controller as its coach.

One pipeline, five stages, one subpackage each; every stage is a plain Python function first and a
command-line verb second. The stage functions are available from the top level::

    import pidlab

    loaded = pidlab.load_model("InvertedPendulum-v5")          # plant
    lin = pidlab.linearize(loaded)                              # linear
    result = pidlab.tune(loaded, preset="robust", lin=lin)      # controller
    region, _ = pidlab.estimate_roa(result.spec, loaded)        # region
    bounds = pidlab.derive_bounds(region, result.spec, loaded)
    spec = pidlab.with_bounds(result.spec, bounds)
    spec = pidlab.with_rescue(spec, pidlab.estimate_rescue(spec, loaded))  # the takeover region
    pidlab.load_region(spec).contains(obs)                      # is this observation in it?
    run = pidlab.train(pidlab.load_recipe("coach/InvertedPendulum-v5.toml"), spec, "runs/demo")  # rl
    env = pidlab.coach_env(gymnasium.make("InvertedPendulum-v5"), spec)  # your own training loop

The subpackages, in pipeline order:

- :mod:`pidlab.plant`: models, model cards, observations, operating points;
- :mod:`pidlab.linear`: linearization and structural analysis;
- :mod:`pidlab.controller`: coach specs, the PID law, loop analysis, auto-tuning, rollouts;
- :mod:`pidlab.region`: regions of attraction and critical-state bounds;
- :mod:`pidlab.rl`: recipes, the coaching wrapper, training, run folders;
- :mod:`pidlab.experiment`: conditions, multi-seed sweeps, statistics;
- :mod:`pidlab.report`: console views, figures, reports;
- :mod:`pidlab.pipeline`: all stages in order (``pidlab run``);
- :mod:`pidlab.cli` and :mod:`pidlab.app`: the command line and the browser tuner.

The names below are imported on first use (PEP 562), so ``import pidlab`` stays cheap: the command
line and worker processes load only the stages they run.
"""

from __future__ import annotations

from importlib import import_module
from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING, Any

try:
    __version__ = version("pidlab")
except PackageNotFoundError:  # pragma: no cover - running from a source tree without install
    __version__ = "0.0.0+unknown"

_EXPORTS = {
    # plant
    "load_model": "pidlab.plant.model",
    "LoadedModel": "pidlab.plant.model",
    "find_card": "pidlab.plant.card",
    "resolve_operating_point": "pidlab.plant.operating_point",
    # linear
    "linearize": "pidlab.linear.linearize",
    "Linearization": "pidlab.linear.linearize",
    "analyze_lti": "pidlab.linear.lti",
    # controller
    "CoachSpec": "pidlab.controller.spec",
    "load_spec": "pidlab.controller.spec",
    "save_spec": "pidlab.controller.spec",
    "Coach": "pidlab.controller.pid",
    "analyze_coach": "pidlab.controller.analysis",
    "tune": "pidlab.controller.autotune",
    "coach_alone": "pidlab.controller.rollout",
    # region
    "estimate_roa": "pidlab.region.roa",
    "derive_bounds": "pidlab.region.bounds",
    "with_bounds": "pidlab.region.bounds",
    "estimate_rescue": "pidlab.region.rescue",
    "with_rescue": "pidlab.region.rescue",
    "load_region": "pidlab.region.takeover",
    # rl
    "Recipe": "pidlab.rl.recipe",
    "load_recipe": "pidlab.rl.recipe",
    "CoachingWrapper": "pidlab.rl.coaching",
    "coach_env": "pidlab.experiment.coach_env",
    "train": "pidlab.rl.train",
    "resume": "pidlab.rl.train",
    "load_agent": "pidlab.rl.agent",
    "TrainedAgent": "pidlab.rl.agent",
    # experiment
    "plan": "pidlab.experiment.sweep",
    "run_sweep": "pidlab.experiment.sweep",
    "analyze_experiment": "pidlab.experiment.analysis",
    # pipeline
    "run_pipeline": "pidlab.pipeline",
    "settings_for": "pidlab.pipeline",
    # errors
    "PidlabError": "pidlab.errors",
}
_RENAMED = {"analyze_experiment": "analyze"}

__all__ = [
    "Coach",
    "CoachSpec",
    "CoachingWrapper",
    "Linearization",
    "LoadedModel",
    "PidlabError",
    "Recipe",
    "TrainedAgent",
    "__version__",
    "analyze_coach",
    "analyze_experiment",
    "analyze_lti",
    "coach_alone",
    "coach_env",
    "derive_bounds",
    "estimate_rescue",
    "estimate_roa",
    "find_card",
    "linearize",
    "load_agent",
    "load_model",
    "load_recipe",
    "load_region",
    "load_spec",
    "plan",
    "resolve_operating_point",
    "resume",
    "run_pipeline",
    "run_sweep",
    "save_spec",
    "settings_for",
    "train",
    "tune",
    "with_bounds",
    "with_rescue",
]

if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs only
    from pidlab.controller.analysis import analyze_coach
    from pidlab.controller.autotune import tune
    from pidlab.controller.pid import Coach
    from pidlab.controller.rollout import coach_alone
    from pidlab.controller.spec import CoachSpec, load_spec, save_spec
    from pidlab.errors import PidlabError
    from pidlab.experiment.analysis import analyze as analyze_experiment
    from pidlab.experiment.sweep import plan, run_sweep
    from pidlab.linear.linearize import Linearization, linearize
    from pidlab.linear.lti import analyze_lti
    from pidlab.pipeline import run_pipeline, settings_for
    from pidlab.plant.card import find_card
    from pidlab.plant.model import LoadedModel, load_model
    from pidlab.plant.operating_point import resolve_operating_point
    from pidlab.region.bounds import derive_bounds, with_bounds
    from pidlab.region.rescue import estimate_rescue, with_rescue
    from pidlab.region.roa import estimate_roa
    from pidlab.region.takeover import load_region
    from pidlab.rl.coaching import CoachingWrapper
    from pidlab.rl.recipe import Recipe, load_recipe
    from pidlab.rl.train import resume, train


def __getattr__(name: str) -> Any:
    """Import a stage function on first use (``pidlab.linearize`` loads :mod:`pidlab.linear`)."""
    if name not in _EXPORTS:
        raise AttributeError(f"module 'pidlab' has no attribute {name!r}")
    value = getattr(import_module(_EXPORTS[name]), _RENAMED.get(name, name))
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
