"""Starts on the floor: a perturbed state of a standing robot, raised or lowered onto its floor.

A robot that stands on a floor (Hopper, Walker2d) rests on soft contacts at its operating point.
Tilting its torso, bending a knee or setting a rate from there leaves its feet inside the floor or
above it, and the first simulator step then throws it with the contact force of the penetration,
or drops it. A start on the floor keeps the state asked for and moves only the height of the root
(its vertical slide joint, or a free joint's height) until the lowest part that touches the floor
sits at the same signed distance from it as at the operating point.

Pure geometry on MuJoCo's own distance (:func:`mujoco.mj_geomDistance`), so it holds for any
geom shapes the floor can collide with. Models without a floor plane under them at the operating
point, or without a vertical root coordinate (the pendulums), have no :class:`Ground` and their
starts are unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

CONTACT_TOLERANCE = 0.01
"""m: at the operating point, a body geom this close to a floor plane stands on it."""

_REACH = 10.0
"""m: distances beyond this are not needed (a geom farther from the floor does not touch it)."""


@dataclass(frozen=True)
class Ground:
    """How a model stands on its floor at the operating point.

    Attributes
    ----------
    pairs : tuple of (int, int)
        (floor plane, body geom) pairs that can collide.
    height_qpos : int
        The ``qpos`` address of the root's height (a vertical slide joint, or a free joint's z).
    clearance : float
        The smallest signed distance over ``pairs`` at the operating point, m (negative: the soft
        contacts press in).
    """

    pairs: tuple[tuple[int, int], ...]
    height_qpos: int
    clearance: float


def _collide(m: mujoco.MjModel, a: int, b: int) -> bool:
    return bool((m.geom_contype[a] & m.geom_conaffinity[b]) or (m.geom_contype[b] & m.geom_conaffinity[a]))


def _height_qpos(m: mujoco.MjModel, d: mujoco.MjData) -> int | None:
    """The ``qpos`` address of the root body's height coordinate, or None."""
    for j in range(m.njnt):
        body = int(m.jnt_bodyid[j])
        if int(m.body_parentid[body]) != 0:
            continue
        kind = int(m.jnt_type[j])
        if kind == int(mujoco.mjtJoint.mjJNT_FREE):
            return int(m.jnt_qposadr[j]) + 2
        if kind == int(mujoco.mjtJoint.mjJNT_SLIDE) and abs(float(d.xaxis[j][2])) > 0.999:
            return int(m.jnt_qposadr[j])
    return None


def clearance(m: mujoco.MjModel, d: mujoco.MjData, pairs: tuple[tuple[int, int], ...]) -> float:
    """The smallest signed distance between the floor and the body over ``pairs``, m.

    Reads ``d``'s geom poses (call :func:`mujoco.mj_kinematics` first).
    """
    fromto = np.zeros(6)
    return min(float(mujoco.mj_geomDistance(m, d, f, g, _REACH, fromto)) for f, g in pairs)


def ground_of(m: mujoco.MjModel, qpos: np.ndarray) -> Ground | None:
    """The :class:`Ground` of ``m`` standing at ``qpos``, or None (no floor under it, no height joint)."""
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_kinematics(m, d)
    height = _height_qpos(m, d)
    planes = [g for g in range(m.ngeom) if int(m.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_PLANE)]
    bodies = [g for g in range(m.ngeom) if int(m.geom_bodyid[g]) != 0]
    pairs = tuple((f, g) for f in planes for g in bodies if _collide(m, f, g))
    if height is None or not pairs:
        return None
    gap = clearance(m, d, pairs)
    if gap > CONTACT_TOLERANCE:
        return None
    return Ground(pairs=pairs, height_qpos=height, clearance=gap)


def on_floor(m: mujoco.MjModel, d: mujoco.MjData, ground: Ground) -> float:
    """Move ``d``'s root height so that its clearance is the operating point's; return the shift, m.

    Changes ``d.qpos`` only (the caller runs :func:`mujoco.mj_forward`). The floor planes are
    horizontal in every model pidlab ships; a tilted plane would need more than the one step taken.
    """
    mujoco.mj_kinematics(m, d)
    shift = ground.clearance - clearance(m, d, ground.pairs)
    d.qpos[ground.height_qpos] += shift
    return shift
