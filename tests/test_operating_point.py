"""Operating points: sources, validation, inverse-dynamics equilibrium control, settling."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from pidlab.errors import KeyframeError, OperatingPointError
from pidlab.plant.model import load_model
from pidlab.plant.operating_point import equilibrium_control, resolve_operating_point, settle

ARM = """
<mujoco>
  <option timestep="0.002"/>
  <worldbody>
    <body name="link1" pos="0 0 1">
      <joint name="j1" type="hinge" axis="0 1 0" damping="0.1"/>
      <geom type="capsule" fromto="0 0 0 0.4 0 0" size="0.03" mass="1"/>
      <body name="link2" pos="0.4 0 0">
        <joint name="j2" type="hinge" axis="0 1 0" damping="0.1"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.025" mass="0.5"/>
      </body>
    </body>
  </worldbody>
  <actuator>
    <motor name="m1" joint="j1" gear="10"/>
    <motor name="m2" joint="j2" gear="4"/>
  </actuator>
  <keyframe><key name="raised" qpos="-0.3 0.5"/></keyframe>
</mujoco>
"""


@pytest.fixture()
def arm(tmp_path):
    path = tmp_path / "arm.xml"
    path.write_text(ARM, encoding="utf-8")
    return load_model(path)


def test_sources(arm):
    op = resolve_operating_point(arm)  # no card: qpos0
    assert op.source == "qpos0" and op.ctrl_source == "zero"
    np.testing.assert_array_equal(op.qpos, [0, 0])
    key = resolve_operating_point(arm, "raised")
    assert key.source == "keyframe:raised"
    np.testing.assert_array_equal(key.qpos, [-0.3, 0.5])
    explicit = resolve_operating_point(arm, "raised", qvel=[0.1, 0.2], ctrl=[0.5, 0.0])
    assert explicit.source == "keyframe:raised+explicit qvel" and explicit.ctrl_source == "explicit"
    with pytest.raises(ValueError):
        explicit.qpos[0] = 1.0  # frozen


def test_equilibrium_control_holds_the_arm_still(arm):
    op = resolve_operating_point(arm, "raised", equilibrium_ctrl=True)
    assert op.ctrl_source == "inverse dynamics"
    assert op.equilibrium.residual_norm < 1e-10
    m = arm.model
    d = mujoco.MjData(m)
    d.qpos[:] = op.qpos
    d.ctrl[:] = op.ctrl
    mujoco.mj_step(m, d, nstep=500)  # one second
    np.testing.assert_allclose(d.qpos, op.qpos, atol=1e-6)
    # and without it the arm falls
    d2 = mujoco.MjData(m)
    d2.qpos[:] = op.qpos
    mujoco.mj_step(m, d2, nstep=500)
    assert np.abs(d2.qpos - op.qpos).max() > 0.1


def test_equilibrium_residual_on_unactuated_dof(models):
    hopper = models["Hopper-v5"]
    eq = equilibrium_control(hopper, hopper.model.qpos0)  # qpos0 hovers above the floor
    # nothing carries the weight: the missing force is on rootz, about m g
    mass = hopper.model.body_subtreemass[0]
    assert eq.residual[1] == pytest.approx(mass * 9.81, rel=1e-6)


def test_settle_finds_standing_hopper(models):
    hopper = models["Hopper-v5"]
    s = settle(hopper, hopper.model.qpos0, ["rootz", "rooty"])
    assert s.equilibrium.residual_norm < 1e-8
    assert 1.15 < s.adjusted["rootz"] < 1.25
    np.testing.assert_allclose(s.qpos, hopper.card.operating_point.qpos, atol=1e-6)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"qpos": [0.0, 0.0, 0.0]}, "qpos has 3 entries; the model expects 2 \\(j1, j2\\)"),
        ({"qvel": [0.0]}, "qvel has 1 entries; the model expects 2"),
        ({"ctrl": [0.0, float("nan")]}, "ctrl has non-finite entries"),
        ({"ctrl": [0.0, 0.0], "equilibrium_ctrl": True}, "not both"),
    ],
)
def test_bad_vectors(arm, kwargs, message):
    with pytest.raises(OperatingPointError, match=message):
        resolve_operating_point(arm, **kwargs)


def test_missing_keyframe(arm, models):
    with pytest.raises(KeyframeError, match="no keyframe 'up' .* one of: raised"):
        resolve_operating_point(arm, "up")
    with pytest.raises(KeyframeError, match="the model defines no keyframes"):
        resolve_operating_point(models["InvertedPendulum-v5"], "up")
