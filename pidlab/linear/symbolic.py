"""Symbolic equations of motion of cart-pole chains, derived with CasADi from MJCF parameters.

An independent route to the linearization of InvertedPendulum and InvertedDoublePendulum:
the Lagrangian of a cart on a slide joint carrying a planar chain of poles on hinge joints is
written out by hand from the compiled model's masses, centre-of-mass offsets, inertias,
damping, armature and gear, and differentiated symbolically. Nothing of MuJoCo's dynamics
pipeline is used, so agreement with :func:`pidlab.linear.linearize.linearize` checks both.

The smooth symbolic model also serves later stages that need derivatives everywhere (e.g.
optimization-based region-of-attraction estimates).
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as cs
import mujoco
import numpy as np

from pidlab.errors import PidlabError


@dataclass(frozen=True)
class LinkParameters:
    """Inertial parameters of one pole, read from the compiled model.

    Attributes
    ----------
    joint : str
        Hinge joint name.
    mass : float
        kg.
    anchor : tuple of float
        Hinge position ``(x, z)`` in the parent body's frame, m.
    com : tuple of float
        Centre of mass ``(x, z)`` in the pole's own frame, relative to the hinge, m.
    inertia : float
        Moment of inertia about the axis through the centre of mass parallel to the hinge
        (y), kg m^2.
    damping, armature : float
        Joint damping (N m s/rad) and armature (kg m^2).
    """

    joint: str
    mass: float
    anchor: tuple[float, float]
    com: tuple[float, float]
    inertia: float
    damping: float
    armature: float


@dataclass(frozen=True)
class CartPoleParameters:
    """Parameters of a cart-pole chain (cart on a slide joint along x, poles hinged about y).

    Attributes
    ----------
    cart_mass : float
        kg (every body moving with the cart).
    cart_damping, cart_armature : float
        Slide joint damping (N s/m) and armature (kg).
    gear : float
        Actuator gear: force on the cart per unit control, N.
    gravity : tuple of float
        Gravity ``(g_x, g_z)`` in m/s^2 (InvertedDoublePendulum's MJCF has ``g_x = 1e-5``).
    links : tuple of LinkParameters
        From the cart outwards.
    """

    cart_mass: float
    cart_damping: float
    cart_armature: float
    gear: float
    gravity: tuple[float, float]
    links: tuple[LinkParameters, ...]


def cart_pole_parameters(model: mujoco.MjModel) -> CartPoleParameters:
    """Read a cart-pole chain's parameters from a compiled MuJoCo model.

    The model must be a slide joint along x followed by hinge joints about y, one per body,
    each body the child of the previous one, driven by one actuator on the slide joint
    (as in InvertedPendulum and InvertedDoublePendulum).

    Raises
    ------
    PidlabError
        The model does not have that structure.
    """
    slide, hinge = int(mujoco.mjtJoint.mjJNT_SLIDE), int(mujoco.mjtJoint.mjJNT_HINGE)
    types = [int(t) for t in model.jnt_type]
    if not types or types[0] != slide or any(t != hinge for t in types[1:]) or model.nu != 1:
        raise PidlabError("not a cart-pole chain: expected one slide joint then hinge joints, one actuator")
    if not np.allclose(model.jnt_axis[0], [1, 0, 0]) or not all(
        np.allclose(model.jnt_axis[j], [0, 1, 0]) for j in range(1, model.njnt)
    ):
        raise PidlabError("not a cart-pole chain: expected the slide along x and the hinges about y")
    if int(model.actuator_trnid[0, 0]) != 0:
        raise PidlabError("not a cart-pole chain: the actuator must drive the slide joint")
    bodies = [int(model.jnt_bodyid[j]) for j in range(model.njnt)]
    for k in range(2, len(bodies)):
        if int(model.body_parentid[bodies[k]]) != bodies[k - 1]:
            raise PidlabError("not a cart-pole chain: each pole must be the child of the previous one")
    links = []
    for j in range(1, model.njnt):
        b = bodies[j]
        flat = np.zeros(9)
        mujoco.mju_quat2Mat(flat, model.body_iquat[b])
        rot = flat.reshape(3, 3)
        inertia = rot @ np.diag(model.body_inertia[b]) @ rot.T
        jpos = model.jnt_pos[j]
        anchor = model.body_pos[b] + _body_rot(model, b) @ jpos
        com = _body_rot(model, b) @ (model.body_ipos[b] - jpos)
        links.append(
            LinkParameters(
                joint=model.joint(j).name,
                mass=float(model.body_mass[b]),
                anchor=(float(anchor[0]), float(anchor[2])),
                com=(float(com[0]), float(com[2])),
                inertia=float(inertia[1, 1]),
                damping=float(model.dof_damping[j]),
                armature=float(model.dof_armature[j]),
            )
        )
    cart_mass = float(
        sum(model.body_mass[b] for b in range(model.nbody) if _moves_only_with_slide(model, b, bodies))
    )
    return CartPoleParameters(
        cart_mass=cart_mass,
        cart_damping=float(model.dof_damping[0]),
        cart_armature=float(model.dof_armature[0]),
        gear=float(model.actuator_gear[0, 0]),
        gravity=(float(model.opt.gravity[0]), float(model.opt.gravity[2])),
        links=tuple(links),
    )


def _body_rot(model: mujoco.MjModel, b: int) -> np.ndarray:
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, model.body_quat[b])
    return rot.reshape(3, 3)


def _moves_only_with_slide(model: mujoco.MjModel, b: int, chain: list[int]) -> bool:
    return b == chain[0]


@dataclass(frozen=True)
class SymbolicCartPole:
    """Symbolic dynamics ``xdot = f(x, u)`` with ``x = (q, qdot)``, ``q = (cart, angles...)``.

    Attributes
    ----------
    params : CartPoleParameters
    f : casadi.Function
        ``f(x, u) -> xdot``, shapes ``(2 n_q,)``, ``(1,)``.
    jac : casadi.Function
        ``jac(x, u) -> (A, B)``.
    """

    params: CartPoleParameters
    f: cs.Function
    jac: cs.Function

    def linearize(self, x0: np.ndarray, u0: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Numeric ``A, B`` at ``(x0, u0)``."""
        A, B = self.jac(np.asarray(x0, dtype=float), float(u0))
        return np.array(A), np.array(B)


def cart_pole_dynamics(params: CartPoleParameters) -> SymbolicCartPole:
    """Derive the Euler-Lagrange equations of a cart-pole chain with CasADi.

    ``T = 1/2 (m_cart + armature) xdot^2 + sum_k [1/2 m_k |v_com,k|^2
    + 1/2 (I_k phidot_k^2 + armature_k thetadot_k^2)]``, ``V = -sum m g . p_com`` over the cart
    and the poles,
    generalized forces ``(gear u - d_cart xdot, -d_k thetadot_k)``, where ``phi_k`` is the
    absolute pole angle (sum of the hinge angles up to ``k``).
    """
    nq = 1 + len(params.links)
    q = cs.SX.sym("q", nq)
    qd = cs.SX.sym("qd", nq)
    u = cs.SX.sym("u")
    kinetic = 0.5 * (params.cart_mass + params.cart_armature) * qd[0] ** 2
    gx, gz = params.gravity
    potential = -params.cart_mass * gx * q[0]
    origin_x: cs.SX = q[0]  # frame of the cart
    origin_z: cs.SX = cs.SX(0.0)
    phi: cs.SX = cs.SX(0.0)
    for k, link in enumerate(params.links):
        # Hinge anchor in the parent's frame, rotated by the parent's absolute angle.
        ax, az = link.anchor
        origin_x = origin_x + cs.cos(phi) * ax + cs.sin(phi) * az
        origin_z = origin_z - cs.sin(phi) * ax + cs.cos(phi) * az
        phi = phi + q[1 + k]
        cx, cz = link.com
        com = cs.vertcat(
            origin_x + cs.cos(phi) * cx + cs.sin(phi) * cz, origin_z - cs.sin(phi) * cx + cs.cos(phi) * cz
        )
        vel = cs.jtimes(com, q, qd)
        phidot = cs.sum1(qd[1 : 2 + k])
        kinetic = kinetic + 0.5 * link.mass * cs.dot(vel, vel) + 0.5 * link.inertia * phidot**2
        kinetic = kinetic + 0.5 * link.armature * qd[1 + k] ** 2
        potential = potential - link.mass * (gx * com[0] + gz * com[1])
    lagrangian = kinetic - potential
    p = cs.gradient(lagrangian, qd)
    mass = cs.jacobian(p, qd)
    generalized = cs.vertcat(
        params.gear * u - params.cart_damping * qd[0],
        *[-link.damping * qd[1 + k] for k, link in enumerate(params.links)],
    )
    rhs = generalized - cs.jtimes(p, q, qd) + cs.gradient(lagrangian, q)
    qdd = cs.solve(mass, rhs)
    x = cs.vertcat(q, qd)
    xdot = cs.vertcat(qd, qdd)
    f = cs.Function("f", [x, u], [xdot], ["x", "u"], ["xdot"])
    jac = cs.Function(
        "f_jacobian", [x, u], [cs.jacobian(xdot, x), cs.jacobian(xdot, u)], ["x", "u"], ["A", "B"]
    )
    return SymbolicCartPole(params=params, f=f, jac=jac)
