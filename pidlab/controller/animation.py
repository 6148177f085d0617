"""The coach alone on the real env, as an animation: record a rollout, draw it, encode a GIF.

Computing and drawing are kept apart: :func:`record_rollout` runs one episode exactly like
:func:`pidlab.controller.rollout.coach_alone` and keeps the joint positions; :func:`render_frames` turns joint
positions into images, either with MuJoCo's offscreen renderer (where the machine has OpenGL) or
with a schematic Pillow drawing (always available); :func:`frames_to_gif` encodes the images.

OpenGL backend
--------------
MuJoCo chooses its OpenGL platform from the ``MUJOCO_GL`` environment variable once, when
``mujoco`` is first imported. A headless server should run with ``MUJOCO_GL=egl`` set *before*
anything imports ``mujoco`` (e.g. in the shell, or at the very top of the entry point);
setting it later has no effect. This module never sets it. Without a usable OpenGL platform,
:func:`offscreen_renderer_available` says why and ``backend="auto"`` draws schematics.

View
----
Both backends look at the x-z plane from the side (+x to the right, +z up) through the same
window: its height fits the robot's largest extent over the rollout. When the model has static
scenery besides the floor (the pendulums' rail), the window is fixed and shows the scenery and the
whole rollout; otherwise it follows the root body's x (kept so that the whole robot stays in view).
"""

from __future__ import annotations

import copy
import io
import math
import threading
import warnings
from dataclasses import dataclass

import mujoco
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from pidlab.controller.pid import Coach
from pidlab.controller.rollout import termination_cause
from pidlab.controller.spec import CoachSpec
from pidlab.errors import PidlabError
from pidlab.plant.envs import make_coach_env
from pidlab.plant.model import LoadedModel

BACKENDS = ("auto", "mujoco", "schematic")
MIN_SIZE = 16
MIN_GIF_FRAME_MS = 20  # browsers play shorter GIF frame delays at ~100 ms

_MARGIN = 1.15  # window size / robot size
_ELEVATION_DEG = -10.0  # MuJoCo camera: slightly from above, so that the floor shows
_GEOM_PLANE = int(mujoco.mjtGeom.mjGEOM_PLANE)
_GEOM_SPHERE = int(mujoco.mjtGeom.mjGEOM_SPHERE)
_GEOM_CAPSULE = int(mujoco.mjtGeom.mjGEOM_CAPSULE)
_GEOM_ELLIPSOID = int(mujoco.mjtGeom.mjGEOM_ELLIPSOID)
_GEOM_CYLINDER = int(mujoco.mjtGeom.mjGEOM_CYLINDER)
_GEOM_BOX = int(mujoco.mjtGeom.mjGEOM_BOX)
_HINGE = int(mujoco.mjtJoint.mjJNT_HINGE)
_BALL = int(mujoco.mjtJoint.mjJNT_BALL)


@dataclass(frozen=True, eq=False)
class Rollout:
    """One episode of the coach alone on the real env, as joint positions.

    Attributes
    ----------
    env_id, spec_name : str
    seed : int
        The episode's ``env.reset(seed=seed)``.
    qpos : np.ndarray
        Shape ``(T + 1, nq)``: the state after reset, then after every env step (read-only).
    rewards : np.ndarray
        Shape ``(T,)``: the reward of every step (read-only).
    total_return : float
    length : int
        ``T``, the number of env steps.
    terminated : bool
        The env terminated (else its time limit truncated the episode).
    cause : str
        ``"time limit"``, or the termination cause as :class:`pidlab.controller.rollout.Episode` names it.
    """

    env_id: str
    spec_name: str
    seed: int
    qpos: np.ndarray
    rewards: np.ndarray
    total_return: float
    length: int
    terminated: bool
    cause: str


@dataclass(frozen=True, eq=False)
class Frames:
    """Images of a rollout, ready to play.

    Attributes
    ----------
    images : tuple of np.ndarray
        Each of shape ``(height, width, 3)``, dtype uint8 (read-only).
    backend : {"mujoco", "schematic"}
    note : str
        How the images were made, e.g. ``"MuJoCo offscreen renderer (EGL)"`` or
        ``"schematic: no OpenGL (<reason>)"``.
    fps : float
        Frames per second that play the rollout in real time (the frames are a subsample).
    """

    images: tuple[np.ndarray, ...]
    backend: str
    note: str
    fps: float


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def record_rollout(
    spec: CoachSpec, loaded: LoadedModel, seed: int = 0, max_steps: int | None = None
) -> Rollout:
    """Run one episode of the coach alone on the real env and keep its joint positions.

    The episode is the one :func:`pidlab.controller.rollout.coach_alone` runs for ``seed0=seed``: same
    actions, same return, same length. Nothing is rendered.

    Parameters
    ----------
    spec : CoachSpec
    loaded : LoadedModel
        The model of ``spec.env_id``.
    seed : int
        ``env.reset(seed=seed)``.
    max_steps : int, optional
        Time limit (default: the env's own, 1000 for the paper envs).

    Returns
    -------
    Rollout
        ``qpos`` of shape ``(T + 1, nq)``, ``rewards`` of shape ``(T,)``.

    Raises
    ------
    PidlabError
        ``max_steps < 1``, or the spec does not fit the model.
    """
    if max_steps is not None and max_steps < 1:
        raise PidlabError(f"max_steps must be >= 1 (or None for the env's own limit), got {max_steps}")
    coach = Coach(spec, loaded)  # checks that the spec is for this env
    limit = {} if max_steps is None else {"max_episode_steps": max_steps}
    env = make_coach_env(spec.env_id, **limit)
    try:
        data = env.unwrapped.data  # type: ignore[attr-defined]
        obs, _ = env.reset(seed=seed)
        coach.reset(obs)
        qpos = [np.array(data.qpos, dtype=float)]
        rewards: list[float] = []
        terminated = truncated = False
        while not (terminated or truncated):
            obs, reward, terminated, truncated, _ = env.step(coach.act(obs))
            rewards.append(float(reward))
            qpos.append(np.array(data.qpos, dtype=float))
        cause = termination_cause(loaded, env) if terminated else "time limit"
    finally:
        env.close()
    total = 0.0
    for r in rewards:  # summed in the same order as coach_alone, so the floats are equal
        total += r
    return Rollout(
        env_id=spec.env_id,
        spec_name=spec.name,
        seed=seed,
        qpos=_readonly(np.array(qpos)),
        rewards=_readonly(np.array(rewards, dtype=float)),
        total_return=total,
        length=len(rewards),
        terminated=bool(terminated),
        cause=cause,
    )


# --- OpenGL probe ------------------------------------------------------------------------------

_probe_lock = threading.Lock()
_probe: tuple[bool, str] | None = None


def _one_line(exc: BaseException, limit: int = 200) -> str:
    text = " ".join(str(exc).split()) or "no message"
    text = f"{type(exc).__name__}: {text}"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _gl_platform() -> str:
    """Name of the OpenGL platform MuJoCo loaded (``"EGL"``, ``"OSMesa"``, ``"GLFW"``...)."""
    try:
        from mujoco.rendering.classic import gl_context

        module = getattr(getattr(gl_context, "GLContext", None), "__module__", "") or ""
    except Exception:
        module = ""
    name = module.rsplit(".", 1)[-1]
    return {"egl": "EGL", "osmesa": "OSMesa", "glfw": "GLFW", "cgl": "CGL"}.get(name, name or "unknown")


def offscreen_renderer_available() -> tuple[bool, str]:
    """Whether ``mujoco.Renderer`` works in this process.

    The first call renders a tiny empty model once; the answer is cached. Any exception
    (no display, no EGL or OSMesa library, ...) makes the answer False, never a crash.
    MuJoCo reads ``MUJOCO_GL`` at import: set ``MUJOCO_GL=egl`` before importing ``mujoco``
    on a headless machine.

    Returns
    -------
    available : bool
    reason : str
        The OpenGL platform when available (e.g. ``"EGL"``), else why not (one line).
    """
    global _probe
    with _probe_lock:
        if _probe is None:
            _probe = _try_renderer()
        return _probe


def _try_renderer() -> tuple[bool, str]:
    renderer = None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # GLFW warns before it fails
            model = mujoco.MjModel.from_xml_string(
                "<mujoco><worldbody><geom size='0.1'/></worldbody></mujoco>"
            )
            renderer = mujoco.Renderer(model, MIN_SIZE, MIN_SIZE)
            data = mujoco.MjData(model)
            mujoco.mj_forward(model, data)
            renderer.update_scene(data)
            image = renderer.render()
            if image.shape != (MIN_SIZE, MIN_SIZE, 3):
                return False, f"the renderer returned an image of shape {image.shape}"
    except Exception as exc:
        return False, _one_line(exc)
    finally:
        if renderer is not None:
            try:
                renderer.close()
            except Exception:
                pass
    return True, _gl_platform()


# --- geometry: what both backends draw ---------------------------------------------------------


@dataclass(frozen=True)
class _Poses:
    """Kinematics of the sampled states, shapes ``(n, ngeom, 3)``, ``(n, ngeom, 3, 3)``..."""

    geom_xpos: np.ndarray
    geom_xmat: np.ndarray
    xanchor: np.ndarray  # (n, njnt, 3)
    root_x: np.ndarray  # (n,)


@dataclass(frozen=True)
class _View:
    """Per-frame window centres ``cx, cz`` (shape ``(n,)``), depth ``cy`` and half-height ``half_h``, m."""

    cx: np.ndarray
    cz: np.ndarray
    cy: float
    half_h: float


def _poses(model: mujoco.MjModel, qpos: np.ndarray) -> _Poses:
    data = mujoco.MjData(model)
    n = len(qpos)
    gx = np.empty((n, model.ngeom, 3))
    gm = np.empty((n, model.ngeom, 3, 3))
    xa = np.empty((n, model.njnt, 3))
    root = 1 if model.nbody > 1 else 0
    rx = np.empty(n)
    for i, q in enumerate(qpos):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        gx[i] = data.geom_xpos
        gm[i] = data.geom_xmat.reshape(-1, 3, 3)
        xa[i] = data.xanchor
        rx[i] = data.xpos[root, 0]
    return _Poses(gx, gm, xa, rx)


def _visible_geoms(model: mujoco.MjModel) -> list[int]:
    return [g for g in range(model.ngeom) if model.geom_group[g] <= 2 and _rgba(model, g)[3] > 0]


def _rgba(model: mujoco.MjModel, g: int) -> np.ndarray:
    rgba = np.array(model.geom_rgba[g], dtype=float)
    mat = int(model.geom_matid[g])
    if mat >= 0 and np.allclose(rgba, (0.5, 0.5, 0.5, 1.0)):  # MuJoCo: the material's colour wins
        rgba = np.array(model.mat_rgba[mat], dtype=float)
    return rgba


def _hull(points: np.ndarray) -> np.ndarray:
    """Convex hull of 2-D points, shape ``(k, 2)``, counter-clockwise (monotone chain)."""
    pts = sorted(set(map(tuple, np.round(points, 9).tolist())))
    if len(pts) <= 2:
        return np.array(pts)

    def cross(o: tuple[float, ...], a: tuple[float, ...], b: tuple[float, ...]) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list[tuple[float, ...]] = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    upper: list[tuple[float, ...]] = []
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return np.array(lower[:-1] + upper[:-1])


_ANGLES = np.linspace(0.0, 2 * np.pi, 24, endpoint=False)
_CIRCLE = np.stack([np.cos(_ANGLES), np.sin(_ANGLES)], axis=1)  # unit circle, shape (24, 2)


def _shape(model: mujoco.MjModel, g: int, pos: np.ndarray, mat: np.ndarray) -> tuple[str, np.ndarray, float]:
    """Projection of geom ``g`` on the x-z plane.

    Returns ``("line", [[x0, z0], [x1, z1]], radius)`` for a capsule (a thick line with round
    caps), ``("circle", [[x, z]], radius)`` or ``("poly", points (k, 2), 0)``.
    """
    gtype = int(model.geom_type[g])
    size = model.geom_size[g]
    xz = [0, 2]
    if gtype == _GEOM_CAPSULE:
        axis = mat[:, 2] * size[1]
        return "line", np.array([(pos - axis)[xz], (pos + axis)[xz]]), float(size[0])
    if gtype == _GEOM_SPHERE:
        return "circle", pos[xz][None, :], float(size[0])
    if gtype == _GEOM_ELLIPSOID:
        a = mat @ np.diag(size)
        cov = a[xz] @ a[xz].T
        chol = np.linalg.cholesky(cov + 1e-12 * np.eye(2))
        return "poly", pos[xz] + _CIRCLE @ chol.T, 0.0
    if gtype == _GEOM_CYLINDER:
        r, h = float(size[0]), float(size[1])
        disc = _CIRCLE[:, :1] * mat[:, 0] * r + _CIRCLE[:, 1:] * mat[:, 1] * r
        pts = np.concatenate([pos + disc + mat[:, 2] * h, pos + disc - mat[:, 2] * h])
        return "poly", _hull(pts[:, xz]), 0.0
    if gtype == _GEOM_BOX:
        center, half = np.zeros(3), np.asarray(size, dtype=float)
    else:  # mesh, height field, SDF: the geom's bounding box
        center, half = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
    corners = pos + (center + signs * half) @ mat.T
    return "poly", _hull(corners[:, xz]), 0.0


def _extent(kind: str, pts: np.ndarray, r: float) -> np.ndarray:
    """``[xmin, xmax, zmin, zmax]`` of a shape."""
    return np.array(
        [pts[:, 0].min() - r, pts[:, 0].max() + r, pts[:, 1].min() - r, pts[:, 1].max() + r], dtype=float
    )


def _union(boxes: list[np.ndarray]) -> np.ndarray:
    b = np.array(boxes)
    return np.array([b[:, 0].min(), b[:, 1].max(), b[:, 2].min(), b[:, 3].max()])


def _view(model: mujoco.MjModel, poses: _Poses, geoms: list[int], aspect: float) -> _View:
    """The window: sized to the robot, fixed when there is static scenery, else following the root."""
    moving = [
        g for g in geoms if model.geom_type[g] != _GEOM_PLANE and model.body_weldid[model.geom_bodyid[g]] != 0
    ]
    static = [
        g for g in geoms if model.geom_type[g] != _GEOM_PLANE and model.body_weldid[model.geom_bodyid[g]] == 0
    ]
    n = len(poses.root_x)
    frame_boxes = []
    for i in range(n):
        boxes = [_extent(*_shape(model, g, poses.geom_xpos[i, g], poses.geom_xmat[i, g])) for g in moving]
        frame_boxes.append(_union(boxes) if boxes else np.array([-0.5, 0.5, -0.5, 0.5]))
    fb = np.array(frame_boxes)
    # show a strip of a floor the robot stands on (or falls to)
    floors = [
        float(poses.geom_xpos[0, g, 2])
        for g in geoms
        if model.geom_type[g] == _GEOM_PLANE and abs(poses.geom_xmat[0, g][2, 2]) > 0.999
    ]
    robot_h = float(np.max(fb[:, 3] - fb[:, 2]))
    near = [z for z in floors if fb[:, 2].min() - 0.5 * robot_h <= z <= fb[:, 3].max()]
    if near:
        fb[:, 2] = np.minimum(fb[:, 2], min(near) - 0.08 * robot_h)
    # the window's half-height fits every frame's robot, and its vertical motion
    size = max(
        float(np.max(fb[:, 1] - fb[:, 0])) / (2 * aspect), float(fb[:, 3].max() - fb[:, 2].min()) / 2, 0.05
    )
    cy = float(np.mean(poses.geom_xpos[0, moving, 1])) if moving else 0.0
    everything = [_union(list(fb))]
    if static:
        everything += [
            _extent(*_shape(model, g, poses.geom_xpos[0, g], poses.geom_xmat[0, g])) for g in static
        ]
        box = _union(everything)
        fixed = max((box[3] - box[2]) / 2, (box[1] - box[0]) / (2 * aspect))
        if fixed <= 4 * size:  # scenery such as a rail: show all of it, and the whole rollout
            half_h = fixed * _MARGIN
            return _View(np.full(n, (box[0] + box[1]) / 2), np.full(n, (box[2] + box[3]) / 2), cy, half_h)
    half_h = size * _MARGIN
    cz = np.full(n, (fb[:, 2].min() + fb[:, 3].max()) / 2)
    half_w = half_h * aspect
    # follow the root body, but keep the whole robot inside the window
    low, high = fb[:, 1] - half_w / _MARGIN, fb[:, 0] + half_w / _MARGIN
    cx = np.clip(poses.root_x, np.minimum(low, high), np.maximum(low, high))
    return _View(cx, cz, cy, half_h)


# --- frames ------------------------------------------------------------------------------------


def _frame_times(n_states: int, max_frames: int, dt: float) -> tuple[np.ndarray, np.ndarray, float]:
    """``(idx, times, fps)``: the drawn states (:func:`_sample`), their times in s, and the real-time fps."""
    steps = n_states - 1
    idx = _sample(n_states, max_frames)
    fps = (len(idx) - 1) / (steps * dt) if steps > 0 else 1.0 / dt
    return idx, idx * dt, fps


def _sample(n_states: int, max_frames: int) -> np.ndarray:
    """Evenly spaced indices into ``n_states`` states, first and last included."""
    k = min(max_frames, n_states)
    if k <= 1:
        return np.zeros(1, dtype=int)
    idx = np.floor(np.linspace(0, n_states - 1, k) + 0.5).astype(int)
    return np.unique(idx)


def render_frames(
    loaded: LoadedModel,
    qpos: np.ndarray,
    *,
    width: int = 320,
    height: int = 240,
    max_frames: int = 120,
    backend: str = "auto",
) -> Frames:
    """Draw the states of a rollout, side on.

    Parameters
    ----------
    loaded : LoadedModel
    qpos : np.ndarray
        Shape ``(T + 1, nq)``: the states, one control period apart (:attr:`Rollout.qpos`).
        States after the first non-finite one are not drawn.
    width, height : int
        Image size in pixels, at least 16.
    max_frames : int
        At most this many frames (at least 2), evenly spaced; the first and last state are
        always drawn.
    backend : {"auto", "mujoco", "schematic"}
        ``"mujoco"``: MuJoCo's offscreen renderer (needs OpenGL); ``"schematic"``: a Pillow
        drawing of the geoms projected on the x-z plane (no OpenGL); ``"auto"``: MuJoCo when
        :func:`offscreen_renderer_available`, else the schematic.

    Returns
    -------
    Frames
        ``images`` each of shape ``(height, width, 3)`` uint8; ``fps`` plays them in real time:
        ``(frames - 1) / (T * control_dt)``.

    Raises
    ------
    PidlabError
        A bad argument, or ``backend="mujoco"`` where the renderer cannot work.
    """
    width, height, max_frames = _check_render_arguments(backend, width, height, max_frames)
    q, suffix = _finite_states(loaded, qpos)
    idx, times, fps = _frame_times(len(q), max_frames, loaded.control_dt)
    model = loaded.model
    poses = _poses(model, q[idx])
    geoms = _visible_geoms(model)
    view = _view(model, poses, geoms, width / height)
    if backend == "schematic":
        images = _render_schematic(loaded, poses, geoms, view, times, width, height)
        return Frames(images, "schematic", f"schematic drawing (x-z plane){suffix}", fps)
    ok, why = offscreen_renderer_available()
    if backend == "mujoco" and not ok:
        raise PidlabError(
            f"MuJoCo's offscreen renderer is not available here ({why}); use backend='schematic', "
            "or set MUJOCO_GL=egl before Python imports mujoco"
        )
    if backend == "mujoco":
        images = _render_mujoco(loaded, q[idx], view, times, width, height)
        return Frames(images, "mujoco", f"MuJoCo offscreen renderer ({why}){suffix}", fps)
    if ok:  # backend "auto"
        try:
            images = _render_mujoco(loaded, q[idx], view, times, width, height)
            return Frames(images, "mujoco", f"MuJoCo offscreen renderer ({why}){suffix}", fps)
        except Exception as exc:  # e.g. the context broke after the probe: still show something
            note = f"schematic: the MuJoCo renderer failed ({_one_line(exc)})"
    else:
        note = f"schematic: no OpenGL ({why})"
    images = _render_schematic(loaded, poses, geoms, view, times, width, height)
    return Frames(images, "schematic", note + suffix, fps)


def _check_render_arguments(backend: str, width: int, height: int, max_frames: int) -> tuple[int, int, int]:
    """``(width, height, max_frames)`` as ints, after checking them and ``backend``."""
    if backend not in BACKENDS:
        raise PidlabError(f"unknown animation backend {backend!r}; expected one of {', '.join(BACKENDS)}")
    if int(width) < MIN_SIZE or int(height) < MIN_SIZE:
        raise PidlabError(f"image size {width}x{height} is too small; width and height must be >= {MIN_SIZE}")
    if int(max_frames) < 2:
        raise PidlabError(f"max_frames must be >= 2, got {max_frames}")
    return int(width), int(height), int(max_frames)


def _finite_states(loaded: LoadedModel, qpos: np.ndarray) -> tuple[np.ndarray, str]:
    """The states up to the first non-finite one, shape ``(T' + 1, nq)``, and a note saying where it cut."""
    model = loaded.model
    q = np.asarray(qpos, dtype=float)
    if q.ndim != 2 or q.shape[0] < 1 or q.shape[1] != model.nq:
        raise PidlabError(
            f"qpos has shape {q.shape}; expected (T + 1, {model.nq}) for {loaded.name} (nq = {model.nq})"
        )
    finite = np.all(np.isfinite(q), axis=1)
    if not finite[0]:
        raise PidlabError("qpos starts with a non-finite state; nothing to draw")
    if finite.all():
        return q, ""
    stop = int(np.argmin(finite))
    return q[:stop], f"; drawn up to step {stop - 1}: the state after it is not finite"


_FONT: ImageFont.ImageFont | ImageFont.FreeTypeFont | None = None


def _font() -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    global _FONT
    if _FONT is None:
        _FONT = ImageFont.load_default()
    return _FONT


def _caption(draw: ImageDraw.ImageDraw, text: str, fill: tuple[int, int, int]) -> None:
    draw.fontmode = "1"  # no anti-aliasing: a schematic keeps a handful of colours (exact GIF palette)
    draw.text((4, 3), text, fill=fill, font=_font())


def _render_mujoco(
    loaded: LoadedModel, qpos: np.ndarray, view: _View, times: np.ndarray, width: int, height: int
) -> tuple[np.ndarray, ...]:
    model = loaded.model
    if width > model.vis.global_.offwidth or height > model.vis.global_.offheight:
        model = copy.copy(model)  # a larger offscreen buffer, without touching the shared model
        model.vis.global_.offwidth = max(width, int(model.vis.global_.offwidth))
        model.vis.global_.offheight = max(height, int(model.vis.global_.offheight))
    data = mujoco.MjData(model)
    camera = mujoco.MjvCamera()
    camera.type = mujoco.mjtCamera.mjCAMERA_FREE
    camera.azimuth = 90.0  # looking along +y: +x to the right, +z up
    camera.elevation = _ELEVATION_DEG
    camera.distance = view.half_h / math.tan(math.radians(float(model.vis.global_.fovy)) / 2)
    images = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        renderer = mujoco.Renderer(model, height, width)
    try:
        # shadows and reflections cost 4-8x the frame time with a software OpenGL (llvmpipe)
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        for i, q in enumerate(qpos):
            data.qpos[:] = q
            mujoco.mj_forward(model, data)
            camera.lookat[:] = (view.cx[i], view.cy, view.cz[i])
            renderer.update_scene(data, camera=camera)
            pixels = np.array(renderer.render(), dtype=np.uint8)
            image = Image.fromarray(pixels)
            bright = float(pixels[:14].mean()) > 110
            _caption(
                ImageDraw.Draw(image), _text(loaded, times[i]), (20, 20, 20) if bright else (240, 240, 240)
            )
            images.append(_readonly(np.asarray(image)))
    finally:
        renderer.close()
    return tuple(images)


def _text(loaded: LoadedModel, t: float) -> str:
    return f"{loaded.name}   t = {t:.2f} s"


def _rgb(rgba: np.ndarray, scale: float = 1.0) -> tuple[int, int, int]:
    r, g, b = (round(255 * min(1.0, max(0.0, float(c) * scale))) for c in rgba[:3])
    return r, g, b


def _covers(pts: np.ndarray, r: float, other: np.ndarray, other_r: float) -> bool:
    """Whether capsule ``(pts, r)`` would hide capsule ``(other, other_r)`` (same place, either way round)."""
    tol = 0.5 * min(r, other_r)
    same = np.max(np.abs(pts - other)) < tol
    flipped = np.max(np.abs(pts - other[::-1])) < tol
    return bool(same or flipped) and r >= 0.8 * other_r


def _tick_spacing(px_per_m: float) -> float:
    for step in (0.1, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0):
        if step * px_per_m >= 40:
            return step
    return 100.0


@dataclass(frozen=True)
class _Schematic:
    """What every schematic frame draws: geoms by role, their colours, the scale in pixels per metre."""

    floors: list[int]  # horizontal planes
    solids: list[int]
    static: set[int]  # solids welded to the world (scenery)
    fill: dict[int, tuple[int, int, int]]
    edge: dict[int, tuple[int, int, int]]
    hinges: list[int]  # hinge and ball joints of moving bodies, drawn as dots
    dot: float  # joint dot radius, px
    scale: float  # px per metre
    width: int
    height: int


@dataclass(frozen=True)
class _Pixels:
    """World ``(x, z)`` to image ``(u, v)`` for a window centred at ``(cx, cz)``."""

    cx: float
    cz: float
    scale: float
    width: int
    height: int

    def __call__(self, p: np.ndarray) -> list[tuple[float, float]]:
        lim = 4.0 * (self.width + self.height)  # clip far-away points so that Pillow gets sane coordinates
        u = np.clip(self.width / 2 + (p[:, 0] - self.cx) * self.scale, -lim, lim)
        v = np.clip(self.height / 2 - (p[:, 1] - self.cz) * self.scale, -lim, lim)
        return list(zip(u.tolist(), v.tolist(), strict=True))


def _schematic(
    model: mujoco.MjModel, poses: _Poses, geoms: list[int], view: _View, width: int, height: int
) -> _Schematic:
    scale = (height / 2) / view.half_h  # pixels per metre
    floors = [
        g
        for g in geoms
        if model.geom_type[g] == _GEOM_PLANE and abs(poses.geom_xmat[0, g][2, 2]) > 0.999  # horizontal planes
    ]
    solids = [g for g in geoms if model.geom_type[g] != _GEOM_PLANE]
    static = {g for g in solids if model.body_weldid[model.geom_bodyid[g]] == 0}
    fill = {g: _rgb(_rgba(model, g)) for g in solids}
    edge = {g: _rgb(_rgba(model, g), 0.55) for g in solids}
    hinges = [
        j
        for j in range(model.njnt)
        if int(model.jnt_type[j]) in (_HINGE, _BALL) and model.body_weldid[model.jnt_bodyid[j]] != 0
    ]
    radii = [float(model.geom_size[g, 0]) for g in solids if model.geom_type[g] == _GEOM_CAPSULE]
    dot = max(1.5, 0.35 * min(radii) * scale) if radii else 2.0
    return _Schematic(floors, solids, static, fill, edge, hinges, dot, scale, width, height)


def _render_schematic(
    loaded: LoadedModel,
    poses: _Poses,
    geoms: list[int],
    view: _View,
    times: np.ndarray,
    width: int,
    height: int,
) -> tuple[np.ndarray, ...]:
    model = loaded.model
    style = _schematic(model, poses, geoms, view, width, height)
    images = []
    for i in range(len(times)):
        cx, cz = float(view.cx[i]), float(view.cz[i])
        px = _Pixels(cx, cz, style.scale, width, height)
        image = Image.new("RGB", (width, height), (255, 255, 255))
        draw = ImageDraw.Draw(image)
        for g in style.floors:
            _draw_floor(draw, px, float(poses.geom_xpos[i, g, 2]), _rgb(_rgba(model, g)))
        # far geoms first (the camera looks along +y), scenery before the robot
        order = sorted(
            style.solids, key=lambda g: (g not in style.static, -float(poses.geom_xpos[i, g, 1]), g)
        )
        drawn: list[tuple[np.ndarray, float, tuple[int, int, int]]] = []
        for g in order:
            kind, pts, r = _shape(model, g, poses.geom_xpos[i, g], poses.geom_xmat[i, g])
            _draw_solid(draw, px, kind, pts, r, style.fill[g], style.edge[g], drawn)
        dot = style.dot
        for j in style.hinges:
            for u, v in px(poses.xanchor[i, j][[0, 2]][None, :]):
                draw.ellipse((u - dot, v - dot, u + dot, v + dot), fill=(40, 40, 40))
        _caption(draw, _text(loaded, float(times[i])), (20, 20, 20))
        images.append(_readonly(np.asarray(image)))
    return tuple(images)


def _draw_floor(draw: ImageDraw.ImageDraw, px: _Pixels, z0: float, colour: tuple[int, int, int]) -> None:
    """A floor at height ``z0``: filled below its line, with ticks along it."""
    (_, v0) = px(np.array([[px.cx, z0]]))[0]
    if v0 >= px.height:
        return
    draw.rectangle((0, max(v0, -1), px.width, px.height), fill=colour)
    draw.line((0, v0, px.width, v0), fill=(90, 90, 90), width=2)
    step = _tick_spacing(px.scale)
    half_w = px.width / 2 / px.scale
    for x in np.arange(math.floor((px.cx - half_w) / step) * step, px.cx + half_w + step, step):
        (u, _) = px(np.array([[x, z0]]))[0]
        draw.line((u, v0, u, v0 + 7), fill=(90, 90, 90), width=1)


def _draw_solid(
    draw: ImageDraw.ImageDraw,
    px: _Pixels,
    kind: str,
    pts: np.ndarray,
    r: float,
    fill: tuple[int, int, int],
    edge: tuple[int, int, int],
    drawn: list[tuple[np.ndarray, float, tuple[int, int, int]]],
) -> None:
    """One geom's projection (:func:`_shape`); capsules go on ``drawn``, to keep hidden ones visible."""
    xy = px(pts)
    if kind == "line":
        rp = max(r * px.scale, 0.75)
        if any(fill != c and _covers(pts, r, o, o_r) for o, o_r, c in drawn):
            rp *= 0.55  # e.g. Walker2d's two legs in the same pose: keep the one behind visible
        drawn.append((pts, r, fill))
        (u0, v0), (u1, v1) = xy
        for rr, colour in ((rp + 1, edge), (rp, fill)):
            draw.line((u0, v0, u1, v1), fill=colour, width=max(1, round(2 * rr)))
            for u, v in xy:
                draw.ellipse((u - rr, v - rr, u + rr, v + rr), fill=colour)
    elif kind == "circle":
        rp = max(r * px.scale, 1.0)
        (u, v) = xy[0]
        draw.ellipse((u - rp, v - rp, u + rp, v + rp), fill=fill, outline=edge, width=1)
    elif len(xy) >= 3:
        draw.polygon(xy, fill=fill, outline=edge, width=1)
    elif xy:
        draw.line(xy + xy[:1], fill=edge, width=1)


# --- GIF ---------------------------------------------------------------------------------------


def _palette(pixels: np.ndarray) -> Image.Image:
    """A "P" image that carries the GIF palette for ``pixels`` (shape ``(h, w, 3)``).

    The exact colours when there are at most 256 (schematics), else 256 median-cut colours.
    """
    packed = (
        (pixels[..., 0].astype(np.uint32) << 16) | (pixels[..., 1].astype(np.uint32) << 8) | pixels[..., 2]
    )
    colours = np.unique(packed)
    if colours.size > 256:
        return Image.fromarray(pixels).quantize(
            256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE
        )
    rgb = np.stack([(colours >> 16) & 255, (colours >> 8) & 255, colours & 255], axis=1).astype(np.uint8)
    table = np.zeros((256, 3), dtype=np.uint8)
    table[: len(rgb)] = rgb
    table[len(rgb) :] = rgb[-1]  # unused entries repeat a used colour, so that nothing maps to them
    image = Image.new("P", (1, 1))
    image.putpalette(table.ravel().tolist())
    return image


def frames_to_gif(frames: Frames) -> bytes:
    """Encode frames as a looping animated GIF.

    All frames share one 256-colour palette (no dithering, so that still parts stay still).
    Each frame lasts ``1000 / fps`` ms, rounded to the GIF's 10 ms unit and at least 20 ms
    (browsers slow down shorter delays). Pillow merges identical consecutive frames into one
    longer frame, so the total duration is kept.

    Parameters
    ----------
    frames : Frames

    Returns
    -------
    bytes
        The GIF file, starting with ``b"GIF89a"``.

    Raises
    ------
    PidlabError
        No images, or images of different sizes.
    """
    if not frames.images:
        raise PidlabError("no frames to encode; render_frames gives at least one")
    shapes = {im.shape for im in frames.images}
    if len(shapes) != 1:
        raise PidlabError(f"frames have different shapes {sorted(shapes)}; expected one (height, width, 3)")
    fps = frames.fps if frames.fps > 0 and math.isfinite(frames.fps) else 10.0
    duration = max(MIN_GIF_FRAME_MS, 10 * round(100.0 / fps))
    rgb = [Image.fromarray(np.ascontiguousarray(im[..., :3], dtype=np.uint8)) for im in frames.images]
    # one palette for all frames, from a few frames stacked
    pick = np.unique(np.linspace(0, len(rgb) - 1, min(6, len(rgb))).round().astype(int))
    montage = np.concatenate([np.asarray(rgb[k]) for k in pick], axis=0)
    palette = _palette(montage)
    indexed = [im.quantize(palette=palette, dither=Image.Dither.NONE) for im in rgb]
    buffer = io.BytesIO()
    indexed[0].save(
        buffer,
        format="GIF",
        save_all=True,
        append_images=indexed[1:],
        duration=duration,
        loop=0,
        optimize=False,
    )
    return buffer.getvalue()
