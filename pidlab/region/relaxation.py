"""Lower bounds of a ``tanh`` network's output over a box: interval and linear relaxation.

A rescue classifier (:class:`pidlab.lookup.RescueClassifier`) scores a state with a network of
``tanh`` hidden layers and one linear output; the model predictor must know the *lowest* score over
a box of states (the forecast's margins about it). Two sound bounds, both computed in the network's
scaled input units, for a batch of boxes of centres ``c`` and half-widths ``r``:

- :func:`interval_lowest`: interval arithmetic, layer by layer (exact for one linear layer, loose
  after a ``tanh``, because every unit's interval forgets which inputs moved it);
- :func:`linear_lowest`: a linear relaxation propagated back to the input (the CROWN scheme of
  Zhang et al., NeurIPS 2018). On its pre-activation interval ``[l, u]`` each ``tanh`` lies between
  two parallel lines of slope ``k = min(tanh'(l), tanh'(u))``, the smallest slope on the interval:
  ``tanh(z) - k z`` does not decrease there, so the line through ``(l, tanh l)`` is below and the line
  through ``(u, tanh u)`` above. The output's coefficients are carried back through every layer,
  each unit taking the line that bounds its term from below, and the result is minimized over the
  input box exactly. The pre-activation intervals of the second and later hidden layers come from
  the same back-substitution (tighter than intervals). The lines' gap shrinks with the square of the
  interval's width, so on the small boxes of a forecast's margins this bound is far tighter.

Neither bound is ever above the true minimum over the box; each ``tanh`` relaxation holds for every
point of its interval, and the intervals contain every pre-activation the box reaches.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pidlab.lookup import RescueClassifier

Layers = Sequence[tuple[np.ndarray, np.ndarray]]
"""``(W, b)`` per layer, ``W`` of shape ``(inputs, outputs)``; ``tanh`` after every layer but the last."""

CHUNK = 512
"""Boxes bounded at once by :func:`linear_lowest` (its coefficients take ``units^2`` floats per box)."""


def lowest_scores(
    classifier: RescueClassifier, points: np.ndarray, margins: np.ndarray, bound: str = "interval"
) -> np.ndarray:
    """A lower bound of a rescue classifier's score over each box ``points +- margins``, shape ``(n,)``.

    No state of the box scores below the bound; with zero margins it is the score itself.

    Parameters
    ----------
    classifier : RescueClassifier
        The network (inputs scaled to [-1, 1] over its domain box).
    points : ndarray
        Box centres, shape ``(n, k)`` (the classifier's variables, in observation units).
    margins : ndarray
        Half-widths per variable, shape ``(k,)`` or ``(n, k)``.
    bound : {"interval", "linear"}
        :func:`interval_lowest` or :func:`linear_lowest` (:data:`pidlab.lookup.BOUNDS`).
    """
    lo, hi = np.array(classifier.lower), np.array(classifier.upper)
    c = classifier.scaled(points)
    r = np.broadcast_to(2.0 * np.abs(np.asarray(margins, dtype=float)) / (hi - lo), c.shape)
    return (linear_lowest if bound == "linear" else interval_lowest)(classifier.layers, c, r)


def interval_lowest(layers: Layers, c: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The interval-arithmetic lower bound of output 0 over each box ``c +- r``, shape ``(n,)``.

    A linear layer maps a box of centre ``c`` and half-widths ``r`` into the box of centre ``c W + b``
    and half-widths ``r |W|`` (exactly); ``tanh``, being increasing, maps an interval's ends to its
    image's.
    """
    last = len(layers) - 1
    for i, (w, b) in enumerate(layers):
        c, r = c @ w + b, r @ np.abs(w)
        if i < last:
            low, high = np.tanh(c - r), np.tanh(c + r)
            c, r = (low + high) / 2.0, (high - low) / 2.0
    return (c - r)[:, 0]


def linear_lowest(layers: Layers, c: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The linear-relaxation lower bound of output 0 over each box ``c +- r``, shape ``(n,)``.

    See the module docstring. ``c`` and ``r``: shape ``(n, inputs)``; done :data:`CHUNK` boxes at a
    time.
    """
    c, r = np.atleast_2d(c), np.broadcast_to(r, np.shape(np.atleast_2d(c)))
    out = np.empty(len(c))
    for s in range(0, len(c), CHUNK):
        out[s : s + CHUNK] = _linear_chunk(layers, c[s : s + CHUNK], r[s : s + CHUNK])
    return out


def tanh_lines(l: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # noqa: E741
    """Two parallel lines about ``tanh`` on ``[l, u]``: slope ``k``, offsets ``below`` and ``above``.

    ``k z + below <= tanh(z) <= k z + above`` for every ``z`` in ``[l, u]`` (elementwise arrays).
    """
    tl, tu = np.tanh(l), np.tanh(u)
    k = 1.0 - np.maximum(tl * tl, tu * tu)  # tanh' = 1 - tanh^2, smallest at the end farther from 0
    return k, tl - k * l, tu - k * u


def _linear_chunk(layers: Layers, c: np.ndarray, r: np.ndarray) -> np.ndarray:
    lines: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    for i in range(len(layers) - 1):
        w, b = layers[i]
        if i == 0:  # a linear map of the box: exact
            mid, rad = c @ w + b, r @ np.abs(w)
            lines.append(tanh_lines(mid - rad, mid + rad))
            continue
        lines.append(tanh_lines(*_back(layers, lines, w.T, b, c, r)))
    w, b = layers[-1]
    return _back(layers, lines, w.T, b, c, r)[0][:, 0]


def _back(
    layers: Layers,
    lines: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    a: np.ndarray,
    const: np.ndarray,
    c: np.ndarray,
    r: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The lowest and highest value over each box of ``a h + const``, ``h`` hidden layer ``len(lines)``.

    ``a``: coefficients, shape ``(m, units)`` (a layer's weights, the same for every box); returns
    two arrays of shape ``(n, m)``. One pass serves both: the highest value is the lowest of
    ``-a h - const`` negated, whose coefficients are ``a``'s negated at every step, so each step
    takes the upper lines where the lower pass takes the lower ones. The first step back is taken as
    matrix products with ``a``'s positive and negative parts (each box's slopes are positive, so
    scaling by them keeps the signs), without the ``(n, m, units)`` array of a per-box step.
    """
    low = np.broadcast_to(np.asarray(const, dtype=float), (len(c), len(a))).copy()
    high = low.copy()
    coef: np.ndarray | None = None  # the per-box coefficients, shape (n, m, units), after the first step
    for j in range(len(lines), 0, -1):
        k, below, above = lines[j - 1]
        w, b = layers[j - 1]
        if coef is None:
            pos, neg = np.maximum(a, 0.0).T, np.minimum(a, 0.0).T
            low += below @ pos + above @ neg
            high += above @ pos + below @ neg
            shift = (k * b) @ a.T
            coef = _shared_times(a, k, w)
        else:
            pos, neg = np.maximum(coef, 0.0), np.minimum(coef, 0.0)
            low += np.einsum("nmd,nd->nm", pos, below) + np.einsum("nmd,nd->nm", neg, above)
            high += np.einsum("nmd,nd->nm", pos, above) + np.einsum("nmd,nd->nm", neg, below)
            coef = coef * k[:, None, :]  # on the pre-activation of layer j
            shift = coef @ b
            coef = coef @ w.T  # on that layer's input
        low += shift
        high += shift
    if coef is None:  # no hidden layer: a linear map of the box
        mid, rad = c @ a.T, r @ np.abs(a).T
    else:
        mid, rad = np.einsum("nmk,nk->nm", coef, c), np.einsum("nmk,nk->nm", np.abs(coef), r)
    return low + mid - rad, high + mid + rad


def _shared_times(a: np.ndarray, k: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``a`` (shape ``(m, units)``) scaled by each box's slopes ``k``, through ``w``: ``(n, m, inputs)``.

    The per-box ``(a * k[i]) @ w.T`` of every box as one matrix product, through whichever
    intermediate array is smaller: the scaled coefficients ``(n, m, units)`` when ``a`` has fewer
    rows than ``w`` has inputs (the output layer's one row), else the scaled weights
    ``(units, n, inputs)`` (a hidden layer's many rows, carried back to a few inputs).
    """
    m, (inputs, units), n = len(a), w.shape, len(k)
    if m <= inputs:
        return ((a[None, :, :] * k[:, None, :]).reshape(n * m, units) @ w.T).reshape(n, m, inputs)
    scaled = k.T[:, :, None] * w.T[:, None, :]  # (units, n, inputs)
    return (a @ scaled.reshape(units, n * inputs)).reshape(m, n, inputs).transpose(1, 0, 2)
