"""The coach alone as an animation: the rollout is coach_alone's episode, the drawings show it.

MuJoCo reads MUJOCO_GL when it is first imported, and conftest.py imports it (through
pidlab.plant.model) before this module runs: setting MUJOCO_GL here would have no effect. So the
in-process MuJoCo-renderer tests run only when pytest itself was started with a working
MUJOCO_GL (e.g. ``MUJOCO_GL=egl pytest``), and one test renders in a child process started with
MUJOCO_GL=egl, so that the EGL path is exercised wherever EGL exists.
"""

from __future__ import annotations

import dataclasses
import io
import itertools
import json
import os
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from PIL import Image

from pidlab.controller.animation import (
    Frames,
    Rollout,
    frames_to_gif,
    offscreen_renderer_available,
    record_rollout,
    render_frames,
)
from pidlab.controller.rollout import coach_alone
from pidlab.controller.spec import CoachSpec, load_spec
from pidlab.errors import PidlabError

TUNING = Path(__file__).resolve().parents[1] / "tuning"
IP = "InvertedPendulum-v5"
CAPTION_ROWS = 16  # the caption (env id, time) is drawn in the top rows

# colours of the InvertedPendulum geoms in the schematic (the model's rgba)
POLE = (0, 178, 178)
CART = (178, 178, 0)
RAIL = (76, 76, 178)


def _spec(env_id: str, preset: str = "pidlab-robust") -> CoachSpec:
    return load_spec(TUNING / f"{env_id}.{preset}.toml")


def _zero_gains(spec: CoachSpec) -> CoachSpec:
    loops = tuple(dataclasses.replace(lp, kp=0.0, ki=0.0, kd=0.0) for lp in spec.loops)
    return dataclasses.replace(spec, loops=loops)


@pytest.fixture(scope="module")
def falling_ip(models) -> Rollout:
    """The IP with a coach that does nothing: the pole falls past 0.2 rad in ~20 steps."""
    return record_rollout(_zero_gains(_spec(IP)), models[IP], seed=1)


def _mask(image: np.ndarray, colour: tuple[int, int, int], tol: int = 3) -> np.ndarray:
    return np.all(np.abs(image.astype(int) - np.array(colour)) <= tol, axis=-1)


def _x_centroid(mask: np.ndarray) -> float:
    return float(np.nonzero(mask)[1].mean())


# --- record_rollout ------------------------------------------------------------------------------


def test_rollout_is_coach_alones_episode_and_starts_at_the_reset_state(models):
    loaded = models[IP]
    spec = _spec(IP)
    rollout = record_rollout(spec, loaded, seed=3)
    episode = coach_alone(spec, loaded, episodes=1, seed0=3).episodes[0]
    assert rollout.total_return == episode.episode_return
    assert rollout.length == episode.length == 1000
    assert (rollout.terminated, rollout.cause) == (episode.terminated, episode.cause) == (False, "time limit")
    assert rollout.qpos.shape == (1001, loaded.model.nq)
    assert rollout.rewards.shape == (1000,)
    assert rollout.rewards.sum() == pytest.approx(rollout.total_return)
    env = gym.make(IP)
    try:
        env.reset(seed=3)
        start = np.array(env.unwrapped.data.qpos)
    finally:
        env.close()
    np.testing.assert_array_equal(rollout.qpos[0], start)
    assert not np.allclose(rollout.qpos[0], 0.0)  # the reset noise is there: it is the real start
    assert not rollout.qpos.flags.writeable


def test_rollout_matches_coach_alone_with_a_time_limit_on_hopper(models):
    loaded = models["Hopper-v5"]
    spec = _spec("Hopper-v5")
    rollout = record_rollout(spec, loaded, seed=2, max_steps=200)
    episode = coach_alone(spec, loaded, episodes=1, seed0=2, max_steps=200).episodes[0]
    assert (rollout.total_return, rollout.length) == (episode.episode_return, episode.length)
    assert rollout.cause == episode.cause
    assert rollout.qpos.shape == (rollout.length + 1, 6)
    assert rollout.length <= 200


def test_falling_rollout_names_the_termination_cause(falling_ip):
    assert falling_ip.terminated and falling_ip.cause == "hinge_pos outside [-0.2, 0.2]"
    assert abs(falling_ip.qpos[-1, 1]) > 0.2 > abs(falling_ip.qpos[0, 1])


# --- schematic -----------------------------------------------------------------------------------


def test_schematic_draws_cart_rail_and_a_pole_that_falls_the_right_way(models, falling_ip):
    frames = render_frames(models[IP], falling_ip.qpos, backend="schematic", width=200, height=150)
    assert frames.backend == "schematic"
    n = falling_ip.length + 1
    assert len(frames.images) == n  # fewer states than max_frames: every state is drawn
    assert frames.fps == pytest.approx((n - 1) / (falling_ip.length * models[IP].control_dt))
    for image in frames.images:
        assert image.shape == (150, 200, 3) and image.dtype == np.uint8
        assert image.std() > 10  # not blank
    first, last = frames.images[0], frames.images[-1]
    body = slice(CAPTION_ROWS, None)
    assert not np.array_equal(first[body], last[body])
    # once the pole has started falling, it moves between consecutive frames
    late = frames.images[n // 2 :]
    assert all(not np.array_equal(a[body], b[body]) for a, b in itertools.pairwise(late))
    for image in (first, last):
        rail_rows = np.nonzero(_mask(image, RAIL).any(axis=1))[0]
        pole_rows = np.nonzero(_mask(image, POLE).any(axis=1))[0]
        assert _mask(image, CART).sum() > 50
        assert rail_rows.size and pole_rows.size
        assert pole_rows.min() < rail_rows.min() - 20  # the pole stands above the rail
    # the pole's top leans to +x (right) when hinge_pos > 0: the hinge axis is +y
    lean = _x_centroid(_mask(last, POLE)) - _x_centroid(_mask(last, CART))
    assert np.sign(lean) == np.sign(falling_ip.qpos[-1, 1]) and abs(lean) > 3


def test_frames_are_an_even_subsample_with_first_and_last_state(models):
    loaded = models[IP]
    q = np.zeros((301, 2))
    q[-1, 1] = 1.2  # only the last state leans (strongly)
    frames = render_frames(loaded, q, backend="schematic", max_frames=7)
    assert len(frames.images) == 7
    assert frames.fps == pytest.approx(6 / (300 * loaded.control_dt))
    leans = [_x_centroid(_mask(im, POLE)) - _x_centroid(_mask(im, CART)) for im in frames.images]
    assert all(abs(v) < 1 for v in leans[:-1]) and leans[-1] > 10


def test_schematic_view_follows_a_robot_that_travels(models):
    loaded = models["Hopper-v5"]
    q = np.tile(loaded.model.qpos0, (101, 1))
    q[:, 0] = np.linspace(0.0, 27.7, 101)  # rootx: 27.7 m, far more than the window is wide
    frames = render_frames(loaded, q, backend="schematic", max_frames=11)
    tan = (204, 153, 102)  # Hopper's rgba (0.8, 0.6, 0.4)
    areas = [_mask(im, tan).sum() for im in frames.images]
    assert min(areas) > 300 and max(areas) < 1.3 * min(areas)  # the whole hopper, in every frame
    # the ground ticks move under it, so the frames are not all the same
    body = slice(CAPTION_ROWS, None)
    assert not np.array_equal(frames.images[0][body], frames.images[1][body])


def test_schematic_walker_shows_both_legs(models):
    loaded = models["Walker2d-v5"]
    rollout = record_rollout(_zero_gains(_spec("Walker2d-v5")), loaded, seed=0, max_steps=60)
    frames = render_frames(loaded, rollout.qpos, backend="schematic", max_frames=3)
    right, left = (204, 153, 102), (178, 76, 153)  # the model's rgba of the right and left legs
    for image in frames.images:
        assert _mask(image, right).sum() > 100 and _mask(image, left).sum() > 100
        # a floor: a grey ground line across the image (the feet hide a bit of it), below the walker
        grey_rows = np.nonzero(_mask(image, (90, 90, 90)).sum(axis=1) > 0.8 * image.shape[1])[0]
        assert grey_rows.size and grey_rows.min() > image.shape[0] // 2


def test_states_after_a_non_finite_one_are_not_drawn(models):
    q = np.zeros((11, 2))
    q[8:] = np.nan
    frames = render_frames(models[IP], q, backend="schematic")
    assert len(frames.images) == 8 and "not finite" in frames.note
    with pytest.raises(PidlabError, match="non-finite"):
        render_frames(models[IP], np.full((3, 2), np.nan), backend="schematic")


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"backend": "opengl"}, "backend"),
        ({"width": 8}, "too small"),
        ({"height": 15}, "too small"),
        ({"max_frames": 1}, "max_frames"),
    ],
)
def test_bad_arguments_raise_pidlab_error(models, kwargs, match):
    with pytest.raises(PidlabError, match=match):
        render_frames(models[IP], np.zeros((5, 2)), **kwargs)


def test_bad_qpos_and_max_steps_raise_pidlab_error(models):
    with pytest.raises(PidlabError, match="shape"):
        render_frames(models[IP], np.zeros((5, 3)), backend="schematic")
    with pytest.raises(PidlabError, match="shape"):
        render_frames(models[IP], np.zeros(2), backend="schematic")
    with pytest.raises(PidlabError, match="max_steps"):
        record_rollout(_spec(IP), models[IP], max_steps=0)
    with pytest.raises(PidlabError, match="not for"):
        record_rollout(_spec(IP), models["Hopper-v5"])


# --- GIF -----------------------------------------------------------------------------------------


def test_gif_loops_with_every_frame_and_real_time_delays(models, falling_ip):
    frames = render_frames(models[IP], falling_ip.qpos, backend="schematic", width=160, height=120)
    data = frames_to_gif(frames)
    assert data.startswith(b"GIF89a")
    with Image.open(io.BytesIO(data)) as gif:
        assert gif.n_frames == len(frames.images)
        assert gif.info["loop"] == 0
        assert gif.info["duration"] == max(20, 10 * round(100 / frames.fps))
        gif.seek(gif.n_frames - 1)
        back = np.asarray(gif.convert("RGB"))
    assert back.shape == frames.images[-1].shape
    assert np.mean(np.abs(back.astype(int) - frames.images[-1].astype(int))) < 2  # palette is faithful


def test_gif_delay_is_at_least_20_ms():
    images = tuple(np.full((16, 16, 3), v, dtype=np.uint8) for v in (0, 255))
    data = frames_to_gif(Frames(images, "schematic", "test", fps=500.0))
    with Image.open(io.BytesIO(data)) as gif:
        assert gif.n_frames == 2 and gif.info["duration"] == 20
    with pytest.raises(PidlabError):
        frames_to_gif(Frames((), "schematic", "test", fps=10.0))


# --- MuJoCo's offscreen renderer -------------------------------------------------------------------


def test_renderer_probe_answers_and_auto_follows_it(models):
    ok, why = offscreen_renderer_available()
    assert isinstance(ok, bool) and why
    assert offscreen_renderer_available() == (ok, why)  # cached
    frames = render_frames(models[IP], np.zeros((3, 2)), backend="auto", width=64, height=48)
    if ok:
        assert frames.backend == "mujoco" and why in frames.note
    else:
        assert frames.backend == "schematic" and frames.note.startswith("schematic: no OpenGL")
        with pytest.raises(PidlabError, match="MUJOCO_GL"):
            render_frames(models[IP], np.zeros((3, 2)), backend="mujoco")


def _need_renderer() -> None:
    ok, why = offscreen_renderer_available()
    if not ok:
        pytest.skip(
            f"MuJoCo offscreen renderer not available in this process ({why}); run with MUJOCO_GL=egl"
        )


def test_mujoco_frames_show_the_pole_leaning_the_right_way(models, falling_ip):
    _need_renderer()
    frames = render_frames(models[IP], falling_ip.qpos, backend="mujoco", max_frames=4)
    assert frames.backend == "mujoco" and len(frames.images) == 4
    for image in frames.images:
        assert image.shape == (240, 320, 3) and image.dtype == np.uint8 and image.std() > 5
    rgb = frames.images[-1].astype(int)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    pole = (g > r + 30) & (b > r + 30)  # cyan, shaded
    cart = (r > b + 30) & (g > b + 30)  # yellow, shaded
    assert pole.sum() > 50 and cart.sum() > 50
    lean = _x_centroid(pole) - _x_centroid(cart)
    assert np.sign(lean) == np.sign(falling_ip.qpos[-1, 1])  # +x is to the right, as in the schematic


def test_mujoco_frames_of_walker_are_not_blank(models):
    _need_renderer()
    loaded = models["Walker2d-v5"]
    q = np.tile(loaded.model.qpos0, (3, 1))
    frames = render_frames(loaded, q, backend="mujoco", width=160, height=120)
    assert len(frames.images) == 3 and all(im.shape == (120, 160, 3) and im.std() > 5 for im in frames.images)


_CHILD = """
import json
import numpy as np
from pidlab.controller.animation import offscreen_renderer_available, render_frames
from pidlab.plant.model import load_model
ok, why = offscreen_renderer_available()
out = {"ok": ok, "why": why}
if ok:
    loaded = load_model("InvertedPendulum-v5")
    q = np.zeros((5, 2)); q[:, 1] = np.linspace(0.0, 0.5, 5)
    frames = render_frames(loaded, q, backend="auto", width=96, height=72, max_frames=3)
    out.update(backend=frames.backend, note=frames.note, n=len(frames.images),
               shapes=[list(im.shape) for im in frames.images], std=[float(im.std()) for im in frames.images],
               differ=bool(np.any(frames.images[0][16:] != frames.images[-1][16:])))
print(json.dumps(out))
"""


def test_egl_renderer_in_a_fresh_process():
    env = {**os.environ, "MUJOCO_GL": "egl"}
    done = subprocess.run(
        [sys.executable, "-c", _CHILD], env=env, capture_output=True, text=True, timeout=120, check=False
    )
    assert done.returncode == 0, done.stderr[-2000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    if not out["ok"]:
        pytest.skip(f"no EGL here: {out['why']}")
    assert out["backend"] == "mujoco" and out["note"] == "MuJoCo offscreen renderer (EGL)"
    assert out["n"] == 3 and out["shapes"] == [[72, 96, 3]] * 3
    assert min(out["std"]) > 5 and out["differ"]
