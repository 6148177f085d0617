"""Searching for the largest clean scale: bisections, and the shrink-until-clean final check.

Every region and bound in :mod:`pidlab.region` is found the same way: a cheap bisection on a
scale (a level, a box factor, a margin) with few samples, then a final check with many
samples at that scale, shrinking it by a fixed factor while anything fails. These helpers take
the check as a callable and hold no state of their own.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

R = TypeVar("R")

FINAL_TRIES = 6
"""How many final checks :func:`shrink_until_clean` runs before it gives up."""


def geometric_bisect(ok: Callable[[float], bool], rounds: int = 8) -> float:
    """Largest factor in (0, 1] for which ``ok`` holds, by geometric bisection; 0 if none.

    Tries 1 first; after a failure with nothing passed yet, quarters the factor; otherwise
    takes the geometric mean of the largest pass and the smallest failure. ``1 + rounds``
    calls of ``ok`` at most.
    """
    if ok(1.0):
        return 1.0
    lo, hi = 0.0, 1.0
    r = 0.25
    for _ in range(rounds):
        if ok(r):
            lo = r
        else:
            hi = r
        r = math.sqrt(lo * hi) if lo > 0 else r / 4.0
    return lo


def halving_bisect(ok: Callable[[float], bool], rounds: int) -> float:
    """Largest factor in (0, 1] for which ``ok`` holds, by plain bisection; 0 if none.

    Tries 1 first and stops if it passes; after a failure with nothing passed yet, halves the
    factor; otherwise takes the midpoint of the largest pass and the smallest failure.
    ``rounds`` calls of ``ok`` at most.
    """
    lo, hi = 0.0, 1.0
    scale = hi
    for _ in range(rounds):
        if ok(scale):
            lo = scale
            if scale == hi:
                break
        else:
            hi = scale
        scale = 0.5 * (lo + hi) if lo > 0 else hi / 2.0
    return lo


@dataclass(frozen=True)
class Shrunk(Generic[R]):
    """The outcome of :func:`shrink_until_clean`.

    Attributes
    ----------
    value : float
        The first value (``start * factor**k``) whose check was clean.
    outcome : R
        What the check returned there.
    tries : int
        Checks run, ``k + 1``.
    """

    value: float
    outcome: R
    tries: int


def shrink_until_clean(
    check: Callable[[float], R],
    clean: Callable[[R], bool],
    start: float,
    factor: float,
    tries: int = FINAL_TRIES,
) -> Shrunk[R] | None:
    """Run ``check`` at ``start``, then shrink the value by ``factor`` until the check is clean.

    Parameters
    ----------
    check : callable
        ``check(value)``: the final check at a value (e.g. simulations from ``N`` samples).
    clean : callable
        ``clean(outcome)``: whether the check found no failure.
    start : float
        The value the bisection found.
    factor : float
        In (0, 1): each failed check multiplies the value by it.
    tries : int
        At most this many checks.

    Returns
    -------
    Shrunk or None
        The first clean value and its outcome; None when all ``tries`` checks failed.
    """
    value = start
    for k in range(tries):
        outcome = check(value)
        if clean(outcome):
            return Shrunk(value, outcome, k + 1)
        value *= factor
    return None
