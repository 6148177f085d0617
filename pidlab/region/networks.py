"""Small ``tanh`` networks fitted deterministically: a classifier region's and a learned forecast's.

Both learned pieces of a spec are two hidden ``tanh`` layers and a linear output, fitted with torch
on one thread from a seed (the caller's random state untouched), and kept as numpy layers
(``(weights, bias)``, weights of shape ``(inputs, outputs)``) that :func:`pidlab.lookup.tanh_forward`
evaluates without torch.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np


def fit_tanh_network(
    inputs: int, outputs: int, width: int, seed: int, train: Callable[[Any], None]
) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """Build ``inputs -> width -> width -> outputs`` from ``seed``, ``train(net)`` it, return its layers.

    Parameters
    ----------
    inputs, outputs, width : int
    seed : int
        Seeds the initial weights and whatever ``train`` draws (shuffles), on a forked random state.
    train : callable
        ``train(net)``: fits the torch module in place.

    Returns
    -------
    tuple of (weights, bias)
        Per layer, float64 weights of shape ``(inputs, outputs)`` and bias.
    """
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            net = torch.nn.Sequential(
                torch.nn.Linear(inputs, width), torch.nn.Tanh(),
                torch.nn.Linear(width, width), torch.nn.Tanh(),
                torch.nn.Linear(width, outputs),
            )  # fmt: skip
            train(net)
    finally:
        torch.set_num_threads(threads)
    linears = [m for m in net if isinstance(m, torch.nn.Linear)]
    return tuple((m.weight.detach().double().numpy().T.copy(), m.bias.detach().double().numpy().copy())
                 for m in linears)  # fmt: skip
