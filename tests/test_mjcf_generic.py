"""Models nobody here wrote: a package's humanoid (free joint, tendons, 17 actuators)."""

from __future__ import annotations

from pathlib import Path

import gymnasium
import numpy as np
import pytest

from pidlab.errors import ModelCompileError, NonFiniteJacobianError, UnknownEnvError
from pidlab.linear.linearize import linearize
from pidlab.linear.lti import analyze_lti
from pidlab.plant.model import load_model
from pidlab.plant.operating_point import resolve_operating_point

ASSETS = Path(gymnasium.__file__).parent / "envs" / "mujoco" / "assets"


def test_packaged_humanoid_with_free_joint_and_tendons():
    loaded = load_model(ASSETS / "humanoid.xml")
    m = loaded.model
    assert m.ntendon > 0 and m.nq == m.nv + 1  # one free joint: a quaternion
    lin = linearize(loaded)
    n = 2 * m.nv
    assert lin.A.shape == (n, n) and lin.B.shape == (n, m.nu)
    assert lin.state_names[:3] == ("root_pos_x", "root_pos_y", "root_pos_z")
    assert lin.input_names[0] == "abdomen_y"
    assert np.all(np.isfinite(lin.A)) and np.all(np.isfinite(lin.Ad))
    # the kinematic rows are exact: d(dq)/dt = qvel
    np.testing.assert_array_equal(lin.A[: m.nv, m.nv :], np.eye(m.nv))
    report = analyze_lti(lin.sys)
    assert report.n == n


def test_floating_arm_names_and_actuators(data_dir):
    loaded = load_model(data_dir / "floating_arm.xml")
    assert loaded.input_names == ("elbow_motor", "extend_motor", "tendon_motor", "shoulder_pos")
    lin = linearize(loaded, resolve_operating_point(loaded, "bent"))
    i_tendon = lin.input_names.index("tendon_motor")
    i_elbow_acc = lin.state_names.index("elbow_vel")
    i_ext_acc = lin.state_names.index("extend_vel")
    # the tendon actuator pushes the elbow and the slide in opposite senses (coef 1 and -0.5)
    assert lin.B[i_elbow_acc, i_tendon] * lin.B[i_ext_acc, i_tendon] < 0


def test_ctrl_on_its_limit_is_differentiated_inwards(data_dir):
    loaded = load_model(data_dir / "floating_arm.xml")
    inside = linearize(loaded, resolve_operating_point(loaded, "bent", ctrl=[0.5, 0, 0, 0]))
    at_limit = linearize(loaded, resolve_operating_point(loaded, "bent", ctrl=[1.0, 0, 0, 0]))
    # the motor's gain does not depend on ctrl: a one-sided difference must give the same column
    np.testing.assert_allclose(at_limit.B[:, 0], inside.B[:, 0], rtol=1e-5, atol=1e-8)


def test_compile_error_carries_mujocos_message(tmp_path):
    bad = tmp_path / "bad.xml"
    bad.write_text("<mujoco><worldbody><body><geom type='sphere'/></body></worldbody></mujoco>")
    with pytest.raises(ModelCompileError, match="MuJoCo could not compile .*size"):
        load_model(bad)


def test_unknown_env_suggests_close_ids():
    with pytest.raises(UnknownEnvError, match="did you mean InvertedPendulum-v5"):
        load_model("InvertedPendulum-v9")


def test_non_finite_jacobian(tmp_path):
    stiff = tmp_path / "stiff.xml"
    stiff.write_text(
        "<mujoco><worldbody><body><joint name='s' type='slide' stiffness='1e308'/>"
        "<geom type='sphere' size='0.1'/></body></worldbody></mujoco>"
    )
    loaded = load_model(stiff)
    with pytest.raises(NonFiniteJacobianError, match="'s_pos' is not finite"):
        linearize(loaded, resolve_operating_point(loaded, qpos=[10.0]))
