"""Exception hierarchy of pidlab.

Every error raised on bad input is a :class:`PidlabError`. Its message says what was wrong,
what was expected and, where it helps, how to fix it, in one line. The CLI prints that line
and exits with code 2.
"""

from __future__ import annotations


class PidlabError(Exception):
    """Base class of every error pidlab raises on bad input or an impossible request."""


class UnknownEnvError(PidlabError, KeyError):
    """A Gymnasium env id that is not registered (and is not an existing MJCF file)."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0]) if self.args else ""


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


class ModelCardError(PidlabError, ValueError):
    """A model card in ``models/`` that is malformed or does not match its model."""


class UnknownSignalError(PidlabError, KeyError):
    """A state or observation variable name that the model does not have."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""
