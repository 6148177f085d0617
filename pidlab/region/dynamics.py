"""A learned one-step model: the linear forecast corrected by a network fitted on recorded transitions.

The discrete linear model (:class:`pidlab.region.forecast.LinearForecast`) is exact to first order
at the operating point and wrong away from it; on InvertedDoublePendulum its forecast of the upper
pole's rate, one control period ahead, misses by up to 2.5 rad/s over the classifier's domain,
more than the rescue region can spare. :func:`fit_residual` fits a small network to what the linear
forecast misses, from the same inputs (the state's deviation from the operating point and the
control's), on transitions recorded behind the exact shield
(:func:`pidlab.rl.calibrate.measure_forecast` with ``model = "learned"``). The corrected forecast is
:class:`pidlab.region.forecast.LearnedForecast`; its error is measured afterwards on transitions the
network never saw, as the linear model's is, and the margins guard the region as before.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from pidlab.lookup import ResidualNet
from pidlab.region.networks import fit_tanh_network

BATCH = 256
"""Transitions per gradient step."""


def fit_residual(
    inputs: np.ndarray,
    residuals: np.ndarray,
    variables: tuple[str, ...],
    width: int = 64,
    epochs: int = 100,
    seed: int = 0,
    blind: tuple[int, ...] = (),
) -> ResidualNet:
    """Fit a two-hidden-layer ``tanh`` network to the linear forecast's residuals, deterministically.

    Inputs and residuals are standardized (the residuals by their standard deviation per variable);
    the loss is the mean squared error, minimized by Adam with a cosine-decayed step size over
    ``epochs`` passes of shuffled batches of :data:`BATCH`, on one thread from ``seed``
    (:func:`pidlab.region.networks.fit_tanh_network`, as the classifier rescue region is fitted).

    Parameters
    ----------
    inputs : ndarray, shape (n, k)
        Per transition, the state's tangent-space deviation and the control's.
    residuals : ndarray, shape (n, len(variables))
        True next observation less the linear forecast, per variable.
    variables : tuple of str
    width, epochs, seed : int
    blind : tuple of int
        Inputs set to 0 before the fit and in every use of the network
        (:func:`pidlab.region.forecast.blind_inputs`).

    Returns
    -------
    ResidualNet
    """
    import torch

    x = np.array(inputs, dtype=float)
    x[:, list(blind)] = 0.0
    y = np.asarray(residuals, dtype=float)
    mean = x.mean(axis=0)
    scale = np.where(x.std(axis=0) > 1e-12, x.std(axis=0), 1.0)
    out = np.where(y.std(axis=0) > 1e-12, y.std(axis=0), 1.0)
    xt = torch.tensor((x - mean) / scale, dtype=torch.float32)
    yt = torch.tensor(y / out, dtype=torch.float32)
    layers = fit_tanh_network(x.shape[1], y.shape[1], width, seed, lambda net: _train(net, xt, yt, epochs))
    return ResidualNet(tuple(variables), tuple(float(v) for v in mean), tuple(float(v) for v in scale),
                       tuple(float(v) for v in out), layers, fitted=len(x), blind=tuple(blind))  # fmt: skip


def _train(net: Any, x: Any, y: Any, epochs: int) -> None:
    import torch

    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)
    for _ in range(epochs):
        order = torch.randperm(len(x))
        for i in range(0, len(x), BATCH):
            b = order[i : i + BATCH]
            loss = torch.mean((net(x[b]) - y[b]) ** 2)
            opt.zero_grad()
            loss.backward()
            opt.step()
        schedule.step()


def fit_error_scale(
    inputs: np.ndarray,
    errors: np.ndarray,
    variables: tuple[str, ...],
    width: int = 64,
    epochs: int = 100,
    seed: int = 0,
    blind: tuple[int, ...] = (),
) -> ResidualNet:
    """Fit a network to the log of a forecast's absolute error, per variable (adaptive margins).

    The target is ``log(error + floor)``, ``floor`` the median error per variable (no log of 0, and
    errors far below the typical one are not told apart); the network (:func:`fit_residual`) then
    gives ``log sigma(z)``, its mean folded into the last layer's bias. What multiple of ``sigma``
    makes a margin is calibrated afterwards on other transitions
    (:class:`pidlab.lookup.MarginScale`).

    Parameters
    ----------
    inputs : ndarray, shape (n, k)
        The linear model's inputs of each transition.
    errors : ndarray, shape (n, len(variables))
        The forecast's absolute error per variable.
    variables : tuple of str
    width, epochs, seed : int
    blind : tuple of int
        As :func:`fit_residual`.

    Returns
    -------
    ResidualNet
        ``correction(z)`` is ``log sigma(z)``.
    """
    err = np.abs(np.asarray(errors, dtype=float))
    floor = np.maximum(np.median(err, axis=0), 1e-12)
    target = np.log(err + floor)
    mean = target.mean(axis=0)
    net = fit_residual(inputs, target - mean, variables, width, epochs, seed, blind)
    *hidden, (w, b) = net.layers
    shifted = (*hidden, (w, b + mean / np.array(net.output_scale)))
    return dataclasses.replace(net, layers=shifted)
