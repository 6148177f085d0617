"""Every exception class of pidlab, in one place (as ``gymnasium/error.py`` keeps Gymnasium's).

Every error raised on bad input is a :class:`PidlabError`. Its message says what was wrong,
what was expected and, where it helps, how to fix it, in one line. A message about a function's
argument starts with the Python parameter's name, ``name=value: ...``, and the error carries that
name in :attr:`PidlabError.param`; the command line replaces it with its own flag (``--seeds 0:
...``), prints the line and exits with code 2.
"""

from __future__ import annotations


class PidlabError(Exception):
    """Base class of every error pidlab raises on bad input or an impossible request.

    Parameters
    ----------
    message : str
        One line: what was wrong, what was expected. When ``param`` is given, the message
        starts with ``f"{param}="``.
    param : str, optional
        The Python parameter whose value was wrong (the CLI maps it to its flag).
    """

    def __init__(self, message: str = "", *, param: str | None = None) -> None:
        super().__init__(message)
        self.param = param


class ArgumentError(PidlabError, TypeError):
    """A Python argument of the wrong kind: ``None`` or a file's path where a loaded object is expected."""


class UnknownEnvError(PidlabError, KeyError):
    """A Gymnasium env id that is not registered (and is not an existing MJCF file)."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


class ProjectError(PidlabError, ValueError):
    """A project file (``pidlab.toml``) that cannot be read or holds a wrong field."""


class ModelCompileError(PidlabError):
    """An MJCF file that MuJoCo cannot load or compile; carries MuJoCo's own message."""


class OperatingPointError(PidlabError, ValueError):
    """A malformed operating point: missing keyframe, wrong-length vector, non-finite entry."""


class KeyframeError(OperatingPointError, KeyError):
    """A keyframe name that the model does not define."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class NonFiniteJacobianError(PidlabError, ArithmeticError):
    """Finite differences produced NaN or inf: the dynamics are not differentiable there."""


class LinearizationError(PidlabError, ValueError):
    """A linearization that cannot be computed as asked (finite-difference step, discretization)."""


class ModelCardError(PidlabError, ValueError):
    """A model card in ``models/`` that is malformed or does not match its model."""


class UnknownSignalError(PidlabError, KeyError):
    """A state or observation variable name that the model does not have."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class RecipeError(PidlabError, ValueError):
    """A malformed recipe: the message names the field and what is allowed."""


class ScheduleError(PidlabError, ValueError):
    """A schedule that cannot be evaluated (unknown shape, begin after finish, ...)."""


class CoachingError(PidlabError, ValueError):
    """A coaching configuration that cannot work (no bounds, unknown mode, wrong env)."""


class SpecError(PidlabError, ValueError):
    """A coach spec that is malformed or does not fit its env."""


class ConditionError(PidlabError, ValueError):
    """A conditions file or a condition name that cannot be used."""


class ExperimentError(PidlabError, ValueError):
    """An experiment that cannot be planned or run as asked."""


class RunDirError(PidlabError):
    """A run directory that cannot be used as asked (exists already, not a run, mismatched resume)."""


class CheckpointError(RunDirError):
    """A checkpoint of a run that cannot be resumed from (a damaged model, statistics, state or log)."""


class RegionError(PidlabError, ValueError):
    """No region of attraction can be given (unstable closed loop, nothing certified)."""


class PipelineError(PidlabError, ValueError):
    """A pipeline that cannot run as asked."""


class AnalysisError(PidlabError, ArithmeticError):
    """A closed loop whose poles or margins are undefined: gains so large that the numbers overflow."""


class OutputError(PidlabError, OSError):
    """A file or folder pidlab was asked to write that cannot be written (read-only, a file, a folder)."""


class BudgetError(PidlabError, ValueError):
    """A budget (episodes, model size) too large to finish in reasonable time; the message says the limit."""


class WorkerLostError(PidlabError, RuntimeError):
    """A worker process that stopped abruptly (killed by a signal, or by the system out of memory)."""


class JobCancelled(Exception):
    """Raised inside a worker when its job was superseded."""
