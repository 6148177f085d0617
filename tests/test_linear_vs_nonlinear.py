"""The discrete model's one-period prediction against MuJoCo stepping, for shrinking perturbations."""

from __future__ import annotations

import itertools

import control as ct
import numpy as np
import pytest

from pidlab.linear import validate
from pidlab.linear.linearize import linearize
from pidlab.plant.model import LoadedModel, load_model
from pidlab.plant.operating_point import resolve_operating_point

SIZES = (1e-2, 1e-3, 1e-4)


def prediction_errors(loaded: LoadedModel, op, sizes=SIZES, seed=0) -> list[float]:
    return list(validate.prediction_errors(loaded, linearize(loaded, op), sizes, seed).errors)


def assert_quadratic(errors: list[float], exact: bool = True) -> None:
    """A tenfold smaller perturbation gives a ~hundredfold smaller error (order 2).

    With ``exact=False`` the order may be higher: at the upright equilibrium the pendulums'
    dynamics are nearly odd-symmetric, the quadratic Taylor term nearly vanishes and the
    error shrinks with the cube.
    """
    for big, small in itertools.pairwise(errors):
        ratio = big / small
        assert ratio > 50, f"errors {errors}: ratio {ratio:.1f} is below quadratic"
        if exact:
            assert ratio < 200, f"errors {errors}: ratio {ratio:.1f} is not quadratic"


@pytest.mark.parametrize("env", ["InvertedPendulum-v5", "InvertedDoublePendulum-v5"])
def test_pendulums_error_shrinks_quadratically(models, env):
    loaded = models[env]
    # a tilted, moving, driven point, where the second-order term is present
    nq = loaded.model.nq
    op = resolve_operating_point(
        loaded, "qpos0", qpos=np.linspace(0.05, 0.12, nq), qvel=np.linspace(-0.3, 0.4, nq), ctrl=[0.3]
    )
    errors = prediction_errors(loaded, op)
    assert_quadratic(errors)
    assert errors[0] < 0.05 * SIZES[0]  # and the linear part is right to begin with


@pytest.mark.parametrize("env", ["InvertedPendulum-v5", "InvertedDoublePendulum-v5"])
def test_pendulums_error_at_equilibrium_is_at_least_quadratic(models, env):
    loaded = models[env]
    errors = prediction_errors(loaded, resolve_operating_point(loaded))
    assert_quadratic(errors, exact=False)
    assert errors[0] < 0.05 * SIZES[0]


def test_free_joint_ball_joint_tendon_model(data_dir):
    """Quaternion-safe: perturbations of the free and ball joints' rotations stay first-order exact."""
    loaded = load_model(data_dir / "floating_arm.xml")
    op = resolve_operating_point(loaded, "bent")
    assert_quadratic(prediction_errors(loaded, op, seed=3))


@pytest.mark.parametrize("env", ["InvertedPendulum-v5", "InvertedDoublePendulum-v5"])
def test_step_model_agrees_with_zoh_of_continuous_model(models, env):
    """For smooth dynamics the integrator-faithful discrete model and ZOH(A, B) agree closely."""
    lin = linearize(models[env])
    zoh = ct.sample_system(lin.sys, lin.control_dt, method="zoh")
    assert np.linalg.norm(lin.Ad - zoh.A) / np.linalg.norm(lin.Ad) < 1e-4
    assert np.linalg.norm(lin.Bd - zoh.B) / np.linalg.norm(lin.Bd) < 1e-4
    zoh_lin = linearize(models[env], discretization="zoh")
    np.testing.assert_allclose(zoh_lin.Ad, zoh.A, rtol=1e-12, atol=1e-12)
