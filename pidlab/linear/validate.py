"""Checks of a linearization against the nonlinear MuJoCo model it came from.

:func:`prediction_errors` steps MuJoCo from perturbed states (its own stepping code, not the
linearizer's) and compares the next state with the discrete model's prediction. For a correct
linearization the error is the Taylor remainder: it shrinks at least quadratically with the
perturbation (a tenfold smaller perturbation, a hundredfold smaller error).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from pidlab.linear.linearize import Linearization
from pidlab.plant.model import LoadedModel


@dataclass(frozen=True)
class PredictionCheck:
    """One-control-period prediction errors of a discrete linear model.

    Attributes
    ----------
    sizes : tuple of float
        Perturbation sizes (Euclidean norm of the tangent-space state perturbation; the
        control perturbation is a tenth of it).
    errors : tuple of float
        ``|x_next(MuJoCo) - x_next(linear)|`` for each size.
    """

    sizes: tuple[float, ...]
    errors: tuple[float, ...]

    @property
    def orders(self) -> tuple[float, ...]:
        """Observed convergence order between successive sizes (2 = quadratic)."""
        out = []
        pairs = list(zip(self.sizes, self.errors, strict=True))
        for (s0, e0), (s1, e1) in itertools.pairwise(pairs):
            out.append(float(np.log(e0 / e1) / np.log(s0 / s1)) if e0 > 0 and e1 > 0 else float("nan"))
        return tuple(out)


def _step(loaded: LoadedModel, lin: Linearization, dx: np.ndarray, du: np.ndarray) -> np.ndarray:
    m = loaded.model
    d = mujoco.MjData(m)
    nv = m.nv
    op = lin.op
    q = op.qpos.copy()
    mujoco.mj_integratePos(m, q, dx[:nv], 1.0)
    d.qpos[:] = q
    d.qvel[:] = op.qvel + dx[nv : 2 * nv]
    if m.na:
        d.act[:] = op.act + dx[2 * nv :]
    d.ctrl[:] = op.ctrl + du
    mujoco.mj_step(m, d, nstep=loaded.frame_skip)
    dq = np.zeros(nv)
    mujoco.mj_differentiatePos(m, dq, 1.0, op.qpos, d.qpos)
    parts = [dq, d.qvel - op.qvel]
    if m.na:
        parts.append(d.act - op.act)
    return np.concatenate(parts)


def prediction_errors(
    loaded: LoadedModel,
    lin: Linearization,
    sizes: Sequence[float] = (1e-2, 1e-3, 1e-4),
    seed: int = 0,
) -> PredictionCheck:
    """Compare the discrete model's one-period prediction with MuJoCo stepping.

    Parameters
    ----------
    loaded : LoadedModel
        The model ``lin`` was computed from.
    lin : Linearization
    sizes : sequence of float
        Perturbation sizes, decreasing.
    seed : int
        Seed of the random perturbation direction (one direction for all sizes).

    Returns
    -------
    PredictionCheck
    """
    rng = np.random.default_rng(seed)
    n, nu = lin.Ad.shape[0], lin.Bd.shape[1]
    raw = np.asarray(rng.standard_normal(n), dtype=float)
    direction = raw / float(np.linalg.norm(raw))
    raw_u = np.asarray(rng.standard_normal(nu), dtype=float)
    udir = raw_u / max(float(np.linalg.norm(raw_u)), 1e-12)
    nominal = _step(loaded, lin, np.zeros(n), np.zeros(nu))
    errors = []
    for size in sizes:
        dx, du = size * direction, 0.1 * size * udir
        actual = _step(loaded, lin, dx, du) - nominal
        errors.append(float(np.linalg.norm(actual - (lin.Ad @ dx + lin.Bd @ du))))
    return PredictionCheck(sizes=tuple(float(s) for s in sizes), errors=tuple(errors))
