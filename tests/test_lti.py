"""Structural properties on textbook systems with known answers."""

from __future__ import annotations

import control as ct
import numpy as np
import pytest

from pidlab.linear.lti import analyze_lti, reachable_dimension, siso_disk_margins, siso_frequency_response


def test_double_integrator():
    sys = ct.ss([[0, 1], [0, 0]], [[0], [1]], [[1, 0]], 0)
    r = analyze_lti(sys)
    assert r.controllable and r.observable and r.n_unstable == 0
    assert all(m.marginal for m in r.modes)
    # measuring only velocity loses the position
    r2 = analyze_lti(ct.ss([[0, 1], [0, 0]], [[0], [1]], [[0, 1]], 0))
    assert r2.observable_dim == 1 and not r2.detectable


def test_uncontrollable_unstable_mode_is_not_stabilizable():
    A = np.diag([2.0, -1.0])
    sys = ct.ss(A, [[0], [1]], np.eye(2), 0)
    r = analyze_lti(sys)
    assert r.controllable_dim == 1 and not r.stabilizable
    unstable = [m for m in r.modes if m.unstable]
    assert len(unstable) == 1 and unstable[0].value == 2.0 and not unstable[0].controllable


def test_discrete_classification():
    sys = ct.ss(np.diag([1.2, 0.5, 1.0]), np.ones((3, 1)), np.eye(3), 0, 0.1)
    r = analyze_lti(sys)
    assert r.discrete and r.dt == 0.1
    assert [m.unstable for m in r.modes] == [False, False, True]
    assert [m.marginal for m in r.modes] == [False, True, False]


def test_staircase_rank_on_badly_scaled_chain():
    # a chain of 8 integrators with gains 1e3: the Kalman matrix spans 1e0..1e21
    n = 8
    A = np.diag(np.full(n - 1, 1e3), -1)
    B = np.zeros((n, 1))
    B[0] = 1.0
    assert reachable_dimension(A, B) == n
    assert np.linalg.matrix_rank(ct.ctrb(A, B)) < n  # what the naive rank says


def test_pendulum_models(models):
    from pidlab.linear.linearize import linearize

    for env, unstable in [("InvertedPendulum-v5", 1), ("InvertedDoublePendulum-v5", 2)]:
        lin = linearize(models[env])
        for sys in (lin.sys, lin.sysd):
            r = analyze_lti(sys)
            assert r.n_unstable == unstable and r.controllable and r.observable
    hopper = linearize(models["Hopper-v5"])
    r = analyze_lti(hopper.sys)
    # rootx is not in the observation: its integrator mode cannot be observed
    assert r.observable_dim == r.n - 1 and not r.detectable


def _random_siso(rng: np.random.Generator, n: int, dt: float | None) -> ct.StateSpace:
    A = rng.standard_normal((n, n)) * 0.5
    if dt is not None:
        A = A / (1.2 * max(abs(np.linalg.eigvals(A))))  # well inside the unit circle
    return ct.ss(A, rng.standard_normal((n, 1)), rng.standard_normal((1, n)), rng.standard_normal((1, 1)), dt)


@pytest.mark.parametrize("dt", [None, 0.02])
def test_fast_frequency_response_and_disk_margins_equal_python_control(dt):
    rng = np.random.default_rng(3)
    omega = np.logspace(-2, np.log10(np.pi / 0.02) - 1e-6, 500)
    for n in (1, 3, 7):
        sys = _random_siso(rng, n, dt)
        ours = siso_frequency_response(sys, omega)
        ref = np.asarray(sys.frequency_response(omega).complex).ravel()
        assert np.allclose(ours, ref, rtol=1e-10, atol=1e-12)
        assert np.allclose(siso_disk_margins(ours), ct.disk_margins(sys, omega), rtol=1e-9)
