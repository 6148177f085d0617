"""Of the actions the exact rescue test vetoes, how many lead where some control still saves the robot.

The exact test (:class:`pidlab.region.oracle.RescueOracle`) vetoes an untrained agent's action when
the coach alone cannot bring the state after it into its certified core within the horizon. That
is the coach's limit, not necessarily the robot's. This script runs the exact-test shield for one
episode (as :func:`pidlab.region.oracle.shield_floor` does: actions ``N(0, 1)`` clipped to the
action range, seed 0), keeps the states after the actions it vetoed, and asks of each whether a
plan of ``--prefix`` actions within the actuator's range, after which the coach acts, brings it into
the same core within the horizon: a sampled search (the cross-entropy method) in the same MuJoCo
model, stopped at the first plan that does. The search starts about the coach's own actions (its
first plan is theirs), so on a state the coach rescues it succeeds at once. A found plan proves the
state savable; none found proves nothing, so the share found is a lower bound on what a stronger
controller could save.

Run: .venv/bin/python benchmarks/beyond_the_coach.py SPEC [--states 40] [--samples 200] [--rounds 8]
[--prefix 20] [--horizon 3]
(InvertedDoublePendulum's room coach: about 10 minutes on one core.)
"""

from __future__ import annotations

import sys
import time

import mujoco
import numpy as np
from bench_cli import Parser, count, fail, positive, run

from pidlab.controller.spec import CoachSpec, load_spec
from pidlab.plant.model import load_model
from pidlab.region.oracle import RescueOracle, reset_states, shield_episode, untrained_agent
from pidlab.region.simulate import Simulator

ELITE = 0.1
"""The share of each round's sequences the next round's distribution is fitted to."""


def shielded_states(oracle: RescueOracle, spec: CoachSpec, seed: int = 0):
    """One episode of the exact-test shield: the states after vetoed actions, and after actions that ran.

    The episode is :func:`~pidlab.region.oracle.shield_floor`'s first for ``seed``. Each state is
    ``(qpos, qvel)`` of the model right after the action, before the coach acts.
    """
    (start,), limit, space = reset_states(spec.env_id, 1, seed)
    vetoed, allowed = [], []

    def seen(x: np.ndarray, action: np.ndarray, ran: bool) -> None:
        (allowed if ran else vetoed).append(after_action(oracle, x, action))

    run_sim = Simulator(spec, oracle.sim.loaded, oracle.lin)
    draw = untrained_agent(space, 1.0, np.random.default_rng(seed))
    shield_episode(oracle, run_sim, start, limit, draw, seen)
    return vetoed, allowed, (space.low.astype(float), space.high.astype(float))


def after_action(oracle: RescueOracle, x_plant: np.ndarray, action: np.ndarray):
    """``(qpos, qvel)`` one control period after ``action`` from the tangent state ``x_plant``."""
    sim = oracle.sim
    sim.start(x_plant)
    sim.d.ctrl[:] = action
    mujoco.mj_step(sim.m, sim.d, nstep=sim.loaded.frame_skip)
    return sim.d.qpos.copy(), sim.d.qvel.copy()


def reaches_core(oracle: RescueOracle, state, plan: np.ndarray) -> tuple[bool, float]:
    """Whether ``plan``, then the coach, brings ``state`` into the core; and a cost (lower is better).

    The plan's actions run first; the coach (reset there) acts for the rest of the horizon. The
    cost ranks failures: a termination by how early it came, else the smallest squared deviation
    of the observation from the operating point on the way.
    """
    sim = oracle.sim
    m, d, fs = sim.m, sim.d, sim.loaded.frame_skip
    mujoco.mj_resetData(m, d)
    d.qpos[:], d.qvel[:] = state
    mujoco.mj_forward(m, d)
    inside = oracle.core.region.contains
    obs, best = sim.observe(), np.inf
    for k in range(oracle.steps):
        if inside(obs):
            return True, -1.0
        if k == len(plan):
            sim.coach.reset(obs)
        d.ctrl[:] = plan[k] if k < len(plan) else sim.coach.act(obs)
        mujoco.mj_step(m, d, nstep=fs)
        obs = sim.observe()
        if sim.terminated(obs):
            return False, 1e3 * (oracle.steps - k)
        dev = obs - sim.y_op
        best = min(best, float(dev @ dev))
    return False, best


def coach_plan(oracle: RescueOracle, state, prefix: int) -> np.ndarray:
    """The coach's own first ``prefix`` actions from ``state`` (the search starts about them)."""
    sim = oracle.sim
    m, d, fs = sim.m, sim.d, sim.loaded.frame_skip
    mujoco.mj_resetData(m, d)
    d.qpos[:], d.qvel[:] = state
    mujoco.mj_forward(m, d)
    obs = sim.observe()
    sim.coach.reset(obs)
    plan = []
    for _ in range(prefix):
        plan.append(np.array(sim.coach.act(obs), dtype=float))
        d.ctrl[:] = plan[-1]
        mujoco.mj_step(m, d, nstep=fs)
        obs = sim.observe()
    return np.array(plan)


def savable(oracle: RescueOracle, state, box, search: tuple[int, int, int], rng: np.random.Generator) -> bool:
    """Whether a sampled plan (``search``: samples, rounds, prefix) then the coach brings ``state`` in.

    The cross-entropy method, started about the coach's own actions: its first plan is theirs.
    """
    samples, rounds, prefix = search
    low, high = box
    mean = coach_plan(oracle, state, prefix)
    std = np.full_like(mean, 0.5 * float(np.max(high - low)))
    n_elite = max(2, int(ELITE * samples))
    for r in range(rounds):
        plans = np.clip(mean + std * rng.standard_normal((samples, *mean.shape)), low, high)
        if r == 0:
            plans[0] = mean
        costs = np.empty(samples)
        for i, plan in enumerate(plans):
            ok, costs[i] = reaches_core(oracle, state, plan)
            if ok:
                return True
        elite = plans[np.argsort(costs)[:n_elite]]
        mean, std = elite.mean(axis=0), elite.std(axis=0) + 0.02
    return False


def main() -> None:
    parser = Parser(description=__doc__.splitlines()[0])
    parser.add_argument("spec", help="A coach spec with a certified core (e.g. the room coach's).")
    parser.add_argument("--states", type=count, default=40, help="Vetoed states searched (default 40).")
    parser.add_argument("--samples", type=count, default=200, help="Plans per search round (default 200).")
    parser.add_argument("--rounds", type=count, default=8, help="Search rounds (default 8).")
    parser.add_argument("--horizon", type=positive, default=3.0, help="The rescue's horizon, s (default 3).")
    parser.add_argument(
        "--prefix", type=count, default=20, help="Planned actions before the coach (default 20)."
    )
    args = parser.parse_args()
    spec = load_spec(args.spec)
    loaded = load_model(spec.env_id)
    oracle = RescueOracle(spec, loaded, horizon_s=args.horizon)
    if oracle.core.region is None or oracle.core.at_end:
        fail(f"{args.spec}: the spec's coach has no certified core (an ellipsoid) to rescue into")
    t0 = time.perf_counter()
    vetoed, allowed, box = shielded_states(oracle, spec)
    rng = np.random.default_rng(0)
    pick = rng.permutation(len(vetoed))[: args.states]
    search = (args.samples, args.rounds, args.prefix)
    found = sum(savable(oracle, vetoed[i], box, search, rng) for i in pick)
    total = len(vetoed) + len(allowed)
    print(f"{spec.env_id}, {spec.name}: one exact-test shield episode, {total:,} steps, "
          f"{len(vetoed):,} actions vetoed ({len(vetoed) / total:.1%})")  # fmt: skip
    print(f"  vetoed states a searched plan brings into the core: {found} of {len(pick)} "
          f"({found / max(len(pick), 1):.0%})")  # fmt: skip
    print(f"  search: {args.samples} plans x {args.rounds} rounds of {args.prefix} actions, then the coach, "
          f"within {oracle.steps} control periods; "
          f"{time.perf_counter() - t0:.0f} s")  # fmt: skip


if __name__ == "__main__":
    run(lambda: sys.exit(main()))
