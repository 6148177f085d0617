"""Coaching schedules: a value as a function of training progress in [0, 1].

A :class:`Schedule` is how coaching fades out over training, so that the agent ends up
independent of its coach. The coaching wrapper reads two of them:

- ``probability``: the chance that the coach intervenes when its trigger fires;
- ``width``: a factor on the critical region's size about its centre (> 1 widens the region in
  which the agent explores freely, so the coach intervenes later and less often).

Between ``begin`` and ``finish`` the value moves from ``start`` to ``end`` along ``shape``;
before ``begin`` it is ``start``, after ``finish`` it is ``end``::

    constant     start throughout
    linear       start + (end - start) * t
    cosine       start + (end - start) * (1 - cos(pi t)) / 2
    exponential  start * (end / start) ** t        (start, end > 0)
    step         start until finish, then end

with ``t = (progress - begin) / (finish - begin)`` clipped to [0, 1].
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from pidlab.checks import number, shown
from pidlab.errors import ScheduleError

SHAPES = ("constant", "linear", "cosine", "exponential", "step")
FIELDS = ("shape", "start", "end", "begin", "finish")


@dataclass(frozen=True)
class Schedule:
    """A value that moves from ``start`` to ``end`` as training progresses.

    Parameters
    ----------
    shape : {"constant", "linear", "cosine", "exponential", "step"}
    start, end : float
        Values before ``begin`` and after ``finish``: finite, >= 0.
    begin, finish : float
        Training progress (fraction of the budget, in [0, 1]) where the change starts and ends.

    Raises
    ------
    ScheduleError
        A shape not in :data:`SHAPES`, a value that is not a finite number in its range (a bool
        is not a number), ``begin > finish``, or an exponential schedule with a zero end.
    """

    shape: str = "constant"
    start: float = 1.0
    end: float = 1.0
    begin: float = 0.0
    finish: float = 1.0

    def __post_init__(self) -> None:
        if not isinstance(self.shape, str) or self.shape not in SHAPES:
            raise ScheduleError(f"schedule shape {shown(self.shape)}: expected one of {', '.join(SHAPES)}")
        for name in ("start", "end"):
            object.__setattr__(
                self, name, number(getattr(self, name), f"schedule {name}", ScheduleError, low=0.0)
            )
        for name in ("begin", "finish"):
            object.__setattr__(
                self, name, number(getattr(self, name), f"schedule {name}", ScheduleError, low=0.0, high=1.0)
            )
        if not self.begin <= self.finish:
            raise ScheduleError(
                f"schedule begin = {self.begin}, finish = {self.finish}: expected 0 <= begin <= finish <= 1"
            )
        if self.shape == "exponential" and not (self.start > 0 and self.end > 0):
            raise ScheduleError("an exponential schedule needs start > 0 and end > 0")

    def __call__(self, progress: float) -> float:
        """The value at ``progress`` (fraction of the training budget spent)."""
        if self.shape == "constant":
            return float(self.start)
        span = self.finish - self.begin
        if span <= 0.0:
            t = 1.0 if progress >= self.finish else 0.0
        else:
            t = min(max((progress - self.begin) / span, 0.0), 1.0)
        if self.shape == "step":
            return float(self.end if progress >= self.finish else self.start)
        if self.shape == "linear":
            return float(self.start + (self.end - self.start) * t)
        if self.shape == "cosine":
            return float(self.start + (self.end - self.start) * (1.0 - math.cos(math.pi * t)) / 2.0)
        return float(self.start * (self.end / self.start) ** t)


def parse_schedule(data: Any, where: str) -> Schedule:
    """Build a :class:`Schedule` from a TOML table (or a bare number: a constant).

    Raises
    ------
    ScheduleError
        Naming ``where`` and what was expected.
    """
    if isinstance(data, (int, float)) and not isinstance(data, bool):
        value = number(data, where, ScheduleError, low=0.0)
        return Schedule("constant", value, value)
    if not isinstance(data, dict) or not all(isinstance(k, str) for k in data):
        raise ScheduleError(
            f"{where} = {shown(data)}: expected a number >= 0 or a table with {', '.join(FIELDS)}"
        )
    unknown = set(data) - set(FIELDS)
    if unknown:
        raise ScheduleError(f"{where}: unknown field(s) {sorted(unknown)}; allowed: {', '.join(FIELDS)}")
    try:
        return Schedule(**data)
    except ScheduleError as exc:
        raise ScheduleError(f"{where}: {exc}") from None


def schedule_to_dict(s: Schedule) -> dict[str, Any]:
    """The TOML table of ``s`` (inverse of :func:`parse_schedule`)."""
    return {"shape": s.shape, "start": s.start, "end": s.end, "begin": s.begin, "finish": s.finish}
