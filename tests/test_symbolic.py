"""pidlab's finite-difference linearization against an independent CasADi derivation."""

from __future__ import annotations

import numpy as np
import pytest

from pidlab.linear.linearize import linearize
from pidlab.linear.symbolic import cart_pole_dynamics, cart_pole_parameters
from pidlab.plant.operating_point import resolve_operating_point


def _assert_rel(actual: np.ndarray, desired: np.ndarray, rtol: float) -> None:
    """Every entry within rtol of the reference entry, or of the matrix scale for ~0 entries."""
    scale = np.abs(desired).max()
    err = np.abs(actual - desired)
    assert np.all(err <= rtol * np.maximum(np.abs(desired), 1e-6 * scale)), (
        f"max relative error {np.max(err / np.maximum(np.abs(desired), 1e-6 * scale)):.3g}"
    )


@pytest.mark.parametrize("env", ["InvertedPendulum-v5", "InvertedDoublePendulum-v5"])
@pytest.mark.parametrize("at", ["card", "qpos0", "tilted"])
def test_matches_symbolic_cart_pole(models, env, at):
    loaded = models[env]
    if at == "tilted":  # away from equilibrium, moving, with control: every term matters
        nq = loaded.model.nq
        op = resolve_operating_point(
            loaded, "qpos0", qpos=np.linspace(0.05, 0.12, nq), qvel=np.linspace(-0.3, 0.4, nq), ctrl=[0.3]
        )
    else:
        op = resolve_operating_point(loaded, at)
    lin = linearize(loaded, op)
    sym = cart_pole_dynamics(cart_pole_parameters(loaded.model))
    x0 = np.concatenate([op.qpos, op.qvel])
    A, B = sym.linearize(x0, float(op.ctrl[0]))
    _assert_rel(lin.A, A, 1e-3)
    _assert_rel(lin.B, B, 1e-3)
    # and the vector field itself
    np.testing.assert_allclose(lin.xdot0, np.array(sym.f(x0, float(op.ctrl[0]))).ravel(), atol=1e-6)


def test_symbolic_parameters_come_from_the_mjcf(models):
    p = cart_pole_parameters(models["InvertedPendulum-v5"].model)
    # gear, damping and the pole's off-axis centre of mass, as written in inverted_pendulum.xml
    assert p.gear == 100.0
    assert p.cart_damping == 1.0 and p.links[0].damping == 1.0
    assert p.links[0].com == pytest.approx((0.0005, 0.3))
    assert p.gravity == pytest.approx((0.0, -9.81))


def test_symbolic_rejects_other_structures(data_dir):
    from pidlab.errors import PidlabError
    from pidlab.plant.model import load_model

    with pytest.raises(PidlabError, match="not a cart-pole chain"):
        cart_pole_parameters(load_model(data_dir / "floating_arm.xml").model)
