"""Lower bounds of a tanh network over a box (pidlab.region.relaxation): sound, and as tight as claimed.

Soundness is checked against the true minimum found by sampling (corners included) on random
networks of one to three hidden layers and boxes of every size; tightness by the order of the gap:
the interval bound's gap to the true minimum shrinks in proportion to the box, the linear
relaxation's with its square.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from pidlab.region.relaxation import interval_lowest, linear_lowest, tanh_lines


def _network(rng: np.random.Generator, sizes: tuple[int, ...]) -> list[tuple[np.ndarray, np.ndarray]]:
    return [
        (rng.normal(0.0, 1.5 / np.sqrt(a), size=(a, b)), rng.normal(0.0, 0.3, size=b))
        for a, b in itertools.pairwise(sizes)
    ]


def _forward(layers, x: np.ndarray) -> np.ndarray:
    for i, (w, b) in enumerate(layers):
        x = x @ w + b
        if i < len(layers) - 1:
            x = np.tanh(x)
    return x[:, 0]


def _sampled_min(layers, c: np.ndarray, r: np.ndarray, rng: np.random.Generator, n: int = 400) -> np.ndarray:
    k = c.shape[1]
    signs = rng.choice([-1.0, 1.0], size=(n // 2, k))
    inner = rng.uniform(-1.0, 1.0, size=(n - n // 2, k))
    offsets = np.vstack([signs, inner])
    points = c[:, None, :] + r[:, None, :] * offsets[None, :, :]
    return _forward(layers, points.reshape(-1, k)).reshape(len(c), n).min(axis=1)


def test_the_two_lines_hold_tanh_between_them() -> None:
    rng = np.random.default_rng(0)
    lo = rng.uniform(-4, 4, size=500)
    hi = lo + rng.uniform(0, 3, size=500)
    k, below, above = tanh_lines(lo, hi)
    for t in np.linspace(0.0, 1.0, 21):
        z = lo + t * (hi - lo)
        assert np.all(k * z + below <= np.tanh(z) + 1e-12)
        assert np.all(np.tanh(z) <= k * z + above + 1e-12)
    assert np.all(k > 0) and np.all(k <= 1)


@pytest.mark.parametrize("sizes", [(3, 8, 1), (4, 16, 16, 1), (2, 6, 5, 4, 1)])
def test_no_state_of_a_box_is_below_either_bound(sizes) -> None:
    rng = np.random.default_rng(len(sizes))
    layers = _network(rng, sizes)
    for half in (1e-3, 0.05, 0.5, 2.0):
        c = rng.uniform(-1.0, 1.0, size=(60, sizes[0]))
        r = np.full_like(c, half) * rng.uniform(0.2, 1.0, size=c.shape)
        truth = _sampled_min(layers, c, r, rng)
        assert np.all(truth >= linear_lowest(layers, c, r) - 1e-9)
        assert np.all(truth >= interval_lowest(layers, c, r) - 1e-9)
    point = rng.uniform(-1, 1, size=(5, sizes[0]))  # a box of no width: the value itself
    assert np.allclose(linear_lowest(layers, point, np.zeros_like(point)), _forward(layers, point))


def _first_order_min(layers, c: np.ndarray, r: np.ndarray) -> np.ndarray:
    """``f(c) - |grad f(c)| . r``: the minimum over the box to first order (backpropagated gradient)."""
    x, slopes = c, []
    for i, (w, b) in enumerate(layers):
        x = x @ w + b
        if i < len(layers) - 1:
            x = np.tanh(x)
            slopes.append(1.0 - x * x)
    grad = np.broadcast_to(layers[-1][0][:, 0], (len(c), layers[-1][0].shape[0]))
    for (w, _), slope in zip(reversed(layers[:-1]), reversed(slopes), strict=True):
        grad = (grad * slope) @ w.T
    return x[:, 0] - np.sum(np.abs(grad) * r, axis=1)


def test_the_linear_gap_shrinks_with_the_square_of_the_box() -> None:
    """Below the first-order minimum, halving the box halves the interval bound's gap and quarters the
    linear relaxation's: the one is loose to first order, the other to second."""
    rng = np.random.default_rng(7)
    layers = _network(rng, (4, 16, 16, 1))
    c = rng.uniform(-0.5, 0.5, size=(40, 4))
    gaps = {}
    for half in (0.02, 0.01):
        r = np.full_like(c, half)
        first = _first_order_min(layers, c, r)
        gaps[half] = (np.median(first - interval_lowest(layers, c, r)), np.median(first - linear_lowest(layers, c, r)))
    interval_ratio, linear_ratio = (gaps[0.02][i] / gaps[0.01][i] for i in range(2))
    assert 1.8 < interval_ratio < 2.2
    assert 3.6 < linear_ratio < 4.4
    assert gaps[0.01][1] < gaps[0.01][0] / 10


def test_the_chunks_give_the_same_bounds_as_one_batch(monkeypatch) -> None:
    import pidlab.region.relaxation as relaxation

    rng = np.random.default_rng(3)
    layers = _network(rng, (3, 8, 8, 1))
    c, r = rng.uniform(-1, 1, size=(50, 3)), np.full((50, 3), 0.1)
    whole = linear_lowest(layers, c, r)
    monkeypatch.setattr(relaxation, "CHUNK", 7)
    assert np.allclose(linear_lowest(layers, c, r), whole, rtol=0.0, atol=1e-12)  # BLAS may round apart


def _extreme(layers, lines, a, const, sign, cb, rb):
    """The lowest (sign 1) or highest (sign -1) of ``a h + const`` over one box, back through ``lines``."""
    a, total = sign * a, sign * const
    for j in range(len(lines), 0, -1):
        k, below, above = lines[j - 1]
        w, b = layers[j - 1]
        total = total + np.where(a > 0, a * below, a * above).sum(axis=1)
        a = a * k
        total = total + a @ b
        a = a @ w.T
    return sign * (total + a @ cb - np.abs(a) @ rb)


def _per_box_linear(layers, c: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The linear relaxation's bound, written out box by box (the reference)."""
    out = []
    for cb, rb in zip(c, r, strict=True):
        lines = []  # (k, below, above) per hidden layer
        for i, (w, b) in enumerate(layers[:-1]):
            if i == 0:
                low, high = cb @ w + b - rb @ np.abs(w), cb @ w + b + rb @ np.abs(w)
            else:
                low = _extreme(layers, lines, w.T, b, 1.0, cb, rb)
                high = _extreme(layers, lines, w.T, b, -1.0, cb, rb)
            lines.append(tanh_lines(low, high))
        w, b = layers[-1]
        out.append(_extreme(layers, lines, w.T, b, 1.0, cb, rb)[0])
    return np.array(out)


@pytest.mark.parametrize("sizes", [(3, 1), (3, 8, 1), (4, 16, 16, 1), (2, 6, 5, 4, 1), (10, 32, 32, 1)])
def test_the_batched_bound_is_the_per_box_relaxation(sizes) -> None:
    """The matrix products that bound every box at once (shared first step, both bounds in one pass) give
    the relaxation of each box computed on its own: the rewrite for speed changed no bound."""
    rng = np.random.default_rng(11)
    layers = _network(rng, sizes)
    c = rng.uniform(-1.0, 1.0, size=(25, sizes[0]))
    r = rng.uniform(0.0, 0.4, size=c.shape)
    assert np.allclose(linear_lowest(layers, c, r), _per_box_linear(layers, c, r), rtol=0.0, atol=1e-12)
