"""Rescue regions: the states from which the coach can still save the episode, found by simulation.

The certified core (:mod:`pidlab.region.roa`) is where the coach provably recovers; it is small,
and a box around the origin cannot follow the slanted band of states the coach actually rescues.
A **rescue region** is estimated instead, in real MuJoCo with the coach's real discrete law and
saturation and the env's termination rule:

1. A lookup grid over two (or three) observation variables — by default the core loop's signal
   and its rate — spans a domain about the operating point. The other variables the estimate
   covers (the **guard**, e.g. the cart) are drawn uniformly from a box about the operating
   point; every remaining state variable stays at the operating point.
2. Each cell is probed at its vertices (with the guard at each corner of its box) and at random
   points. A probe is *rescued* when, from it,
   the coach brings it into the spec's **certified core** without a termination on the way: for
   a Lyapunov-certified coach, the trajectory enters the certified level set within the horizon
   (from there on recovery is certified, so the simulation stops); for a coach certified by
   simulation only (contacts), it survives the whole horizon, the criterion its recoverable box
   was certified by.
   For the ``reactive`` trigger the probe first takes one agent step at each corner of the
   action box scaled by ``action_fraction`` (the worst the agent can do before the check); for
   the ``predictive`` trigger there is no such step, since the trigger vets the agent's action
   before it runs.
3. A cell is marked when all its probes are rescued; the marked cells connected to the operating
   point's cell form the region.
4. **Validation**: fresh states drawn uniformly in the region (``validation`` of them, 2,000 by
   default) are simulated. A failure unmarks its cell and a new fresh draw follows, until a
   draw has no failure (rule of three: a failure rate below ``3 / validation`` with 95 %
   confidence).
5. **Coverage**: fresh states drawn uniformly over the whole domain tell which are rescuable; the
   coverage is the fraction of those the region contains. The certified core and the spec's
   takeover box are scored on the same states.

``action_fraction=None`` asks for the full action range when the coach can rescue the
operating point's cell after it, else the largest fraction (bisection) it can; the choice is
recorded.
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
from scipy import ndimage

from pidlab import __version__
from pidlab.checks import instance, integer, number, shown
from pidlab.checks import seed as check_seed
from pidlab.controller.pid import Coach
from pidlab.controller.spec import CoachSpec, law_digest
from pidlab.errors import RegionError
from pidlab.linear.linearize import Linearization
from pidlab.lookup import TRIGGERS, LookupGrid
from pidlab.parallel import resolve_workers
from pidlab.plant.card import ModelCard
from pidlab.plant.model import LoadedModel, model_digest
from pidlab.region.bounds import MAX_VERTICES, _action_vertices
from pidlab.region.journal import CHUNK, LabelJournal, Outcome, Start, journal_key
from pidlab.region.shrink import halving_bisect
from pidlab.region.simulate import SimulationPool, Simulator, horizon_steps
from pidlab.region.takeover import BoxRegion, EllipsoidRegion, GridRegion, region_from_bounds

Progress = Callable[[str, "float | None"], None]

MAX_ROUNDS = 12
"""Validation draws before the estimate gives up."""

STARTS_ON_FLOOR = "on the floor: the root's height moved until the feet touch it as at the operating point"
"""Provenance of a region whose simulations started on the floor (a model standing on one)."""


@dataclass(frozen=True)
class RescueSettings:
    """What a rescue-region estimate covers and how hard it looks.

    Attributes
    ----------
    variables : tuple of str
        Grid variables (observation names of a hinge or slide joint's position, its sine, or
        its velocity).
    half_range : tuple of float
        The grid's half-widths about the operating point's observation.
    cells : tuple of int
        Cells per grid variable.
    guard : dict
        ``variable -> half-width`` about the operating point: other variables drawn uniformly.
    trigger : {"predictive", "reactive"}
    action_fraction : float or None
        ``reactive``: the agent step's size as a fraction of the action range (``None``: the full
        range if the coach can handle it, else the largest it can). ``predictive``: unused (0).
    probes : int
        Random states simulated per cell after its vertices.
    horizon_s : float
        Simulated time per rescue.
    validation : int
        Fresh states per validation draw.
    coverage : int
        Fresh states over the domain for the coverage.
    seed : int
    """

    variables: tuple[str, ...]
    half_range: tuple[float, ...]
    cells: tuple[int, ...]
    guard: dict[str, float] = field(default_factory=dict, compare=False, hash=False)
    trigger: str = "predictive"
    action_fraction: float | None = None
    probes: int = 2
    horizon_s: float = 3.0
    validation: int = 2000
    coverage: int = 2000
    seed: int = 0

    def __post_init__(self) -> None:
        """Refuse settings out of range at once (:class:`RegionError` naming the field)."""
        _check_settings(self)


@dataclass(frozen=True)
class Coverage:
    """How much of the rescuable set some region holds, on one draw over the domain.

    Attributes
    ----------
    samples : int
        States drawn over the domain.
    rescuable : int
        Of those, the ones the coach rescues.
    contained : dict
        Region name -> rescuable states it contains (``rescue``, ``core``, ``takeover box``, ...).
    volume : dict
        Region name -> share of all drawn states it contains (its size in the domain).
    """

    samples: int
    rescuable: int
    contained: dict[str, int]
    volume: dict[str, float]

    def fraction(self, name: str) -> float:
        """Coverage of region ``name``: contained rescuable states / rescuable states."""
        return self.contained[name] / self.rescuable if self.rescuable else float("nan")


@dataclass(frozen=True)
class RescueRegion:
    """A validated rescue region, with what was measured on it.

    Attributes
    ----------
    env_id, spec_name : str
    grid : LookupGrid
        The region (marked cells, guard box, trigger, action fraction).
    settings : RescueSettings
        With the action fraction actually used.
    validation : tuple of int
        ``(samples, failures)`` of the final draw (failures is 0).
    rounds : int
        Validation draws it took.
    unmarked : int
        Cells the validation draws unmarked.
    coverage : Coverage
    elapsed_s : float
    provenance : dict
    reused : int
        Of the simulations, the outcomes read from a journal instead of simulated (a resumed run).
    """

    env_id: str
    spec_name: str
    grid: LookupGrid
    settings: RescueSettings
    validation: tuple[int, int]
    rounds: int
    unmarked: int
    coverage: Coverage
    elapsed_s: float
    provenance: dict[str, Any] = field(default_factory=dict, compare=False, hash=False)
    reused: int = field(default=0, compare=False)

    @property
    def failure_bound_95(self) -> float:
        """Rule of three: the failure rate in the region is below this with 95 % confidence."""
        return 3.0 / self.validation[0]

    def to_table(self) -> dict[str, Any]:
        """The spec's ``[bounds.rescue]`` table."""
        return {**self.grid.to_table(), "provenance": dict(self.provenance)}


@dataclass(frozen=True)
class _Domain:
    """The estimate's state space: grid and guard variables, their columns and the way to MuJoCo."""

    grid_vars: tuple[str, ...]
    guard_vars: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    guard_lo: np.ndarray
    guard_hi: np.ndarray
    addr: tuple[tuple[str, int, int, str], ...]
    """Per variable (grid then guard): (source, qpos or qvel address, dof address, transform)."""

    def guard_box(self) -> tuple[tuple[str, ...], np.ndarray, np.ndarray]:
        """The guard variables with their lower and upper limits."""
        return self.guard_vars, self.guard_lo, self.guard_hi

    def to_plant(self, values: np.ndarray, sim: Simulator) -> np.ndarray:
        """Tangent deviation ``(dq, dv)`` from the operating point with these variables set."""
        m, op = sim.m, sim.lin.op
        x = np.zeros(2 * m.nv)
        for v, (source, adr, dof, transform) in zip(values, self.addr, strict=True):
            if source == "qpos":
                angle = float(np.arcsin(np.clip(v, -1.0, 1.0))) if transform == "sin" else float(v)
                x[dof] = angle - op.qpos[adr]
            else:
                x[m.nv + dof] = v - op.qvel[adr]
        return x


def _domain(settings: RescueSettings, card: ModelCard, loaded: LoadedModel, y_op: np.ndarray) -> _Domain:
    """Check the variables and lay out the domain about the operating point's observation."""
    grid = state_domain(settings.variables, settings.half_range, card, loaded, y_op)
    guard = state_domain(tuple(settings.guard), tuple(settings.guard.values()), card, loaded, y_op)
    return _Domain(
        grid.grid_vars, guard.grid_vars, grid.lower, grid.upper, guard.lower, guard.upper,
        grid.addr + guard.addr,
    )  # fmt: skip


def state_domain(
    names: tuple[str, ...],
    half_range: tuple[float, ...],
    card: ModelCard,
    loaded: LoadedModel,
    y_op: np.ndarray,
) -> _Domain:
    """A box of ``names`` (no guard) about the operating point's observation, laid out for MuJoCo.

    Raises
    ------
    RegionError
        A variable that is not a joint's position, its sine or its velocity.
    """
    m = loaded.model
    addr = []
    for name in names:
        var = card.variable(name)
        if var.source not in ("qpos", "qvel") or var.transform not in ("identity", "sin"):
            raise RegionError(
                f"{name}: a rescue region's variable must be a joint's position, its sine or its velocity"
            )
        jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, var.joint)
        adr = int(m.jnt_qposadr[jid]) if var.source == "qpos" else int(m.jnt_dofadr[jid])
        addr.append((var.source, adr, int(m.jnt_dofadr[jid]), var.transform))
    col = card.observation_names
    centre = np.array([y_op[col.index(n)] for n in names], dtype=float)
    half = np.array(half_range, dtype=float)
    empty = np.zeros(0)
    return _Domain(tuple(names), (), centre - half, centre + half, empty, empty, tuple(addr))


RESCUE_ENDS = ("core", "box")
"""Where a rescue ends (:func:`_core`): the certified core (a coach certified by simulation: the
horizon held), or the recoverable box ``[bounds.box]`` at the horizon's end (held, and upright)."""


def check_into(into: str) -> None:
    """Refuse an unknown end of a rescue (a :class:`RegionError` naming ``into``)."""
    if into not in RESCUE_ENDS:
        raise RegionError(f"into={into!r}: expected one of {', '.join(RESCUE_ENDS)}", param="into")


@dataclass(frozen=True)
class _Core:
    """What a rescue must achieve: enter the certified core (``region``), or (None) survive the horizon.

    With ``at_end``, survive the horizon and end it in ``region`` (a box that is not invariant: a
    fall can cross it on its way down).
    """

    region: Any
    at_end: bool = False


def _core(spec: CoachSpec, card: ModelCard, into: str = "core") -> _Core:
    """Where a rescue ends (:data:`RESCUE_ENDS`).

    ``into = "core"``: the spec's certified core, its Lyapunov level set (to be entered), else
    survival of the horizon: a coach certified by simulation only (a recoverable box) has no
    certificate to enter, its box was certified by surviving the horizon, and so is a rescue.
    ``into = "box"``: survive the horizon and end it in the spec's recoverable box
    (``[bounds.box]``): back near the operating point and slow, not merely still standing. (Not
    "enter it": the box tests only the coached variables, and a fall crosses it on its way down.)

    Raises
    ------
    RegionError
        The spec has neither (no ``pidlab bounds`` yet), or no box for ``into = "box"``.
    """
    b = spec.bounds or {}
    names = card.observation_names
    if into == "box":
        if not b.get("box"):
            raise RegionError(
                f"{spec.name}: a rescue into the recoverable box needs [bounds.box]; run `pidlab bounds "
                "SPEC --write` first, or rescue into the core"
            )
        return _Core(BoxRegion(b["box"], names), at_end=True)
    if b.get("ellipsoid"):
        return _Core(EllipsoidRegion(b["ellipsoid"], names, certified=True))
    if b.get("box"):
        return _Core(None)
    raise RegionError(
        f"{spec.name}: the spec has no certified core ([bounds]); run `pidlab bounds SPEC --write` first"
    )


def _rescued(
    sim: Simulator,
    item: tuple[np.ndarray, np.ndarray | None],
    steps: int,
    core: _Core,
    grounded: bool = False,
) -> tuple[bool, np.ndarray]:
    """Whether the coach rescues the state ``item[0]`` (after the agent step ``item[1]``), and its obs.

    A task of :meth:`~pidlab.parallel.WorkerPool.run`. ``grounded``: the start is put on the floor
    (:meth:`Simulator.start`).
    """
    x, v = item
    obs0 = sim.start(x, grounded=grounded)
    m, d, card, frame_skip = sim.m, sim.d, sim.fast, sim.loaded.frame_skip
    if card.terminated(d, obs0):  # the env would have ended it: no rescue starts there
        return False, obs0
    obs = obs0
    if v is not None:
        d.ctrl[:] = sim.lin.op.ctrl + v
        mujoco.mj_step(m, d, nstep=frame_skip)
        obs = card.observe(d)
        if card.terminated(d, obs):
            return False, obs0
        sim.coach.reset(obs)
    entered = core.region.contains if core.region is not None and not core.at_end else None
    act = sim.coach.act
    for _ in range(steps):
        if entered is not None and entered(obs):
            return True, obs0
        d.ctrl[:] = act(obs)
        mujoco.mj_step(m, d, nstep=frame_skip)
        obs = card.observe(d)
        if card.terminated(d, obs):
            return False, obs0
    if core.at_end:
        return bool(core.region.contains(obs)), obs0
    return entered is None, obs0


@dataclass
class _Estimate:
    """The estimate's working state: pool, domain, kicks, random stream, accounts."""

    pool: SimulationPool
    domain: _Domain
    settings: Any
    """A :class:`RescueSettings` (the grid estimate), or a classifier's settings."""
    kicks: list[np.ndarray | None]
    steps: int
    core: _Core
    rng: np.random.Generator
    report: Progress
    simulations: int = 0
    grounded: bool = False
    """Starts are put on the floor (a model that stands on one at its operating point)."""
    journal: LabelJournal | None = None
    """Where outcomes are kept as they are found, and found again (None: nowhere)."""
    reused: int = 0
    """Of :attr:`simulations`, the outcomes read from the journal instead of simulated."""

    def rescued(self, values: np.ndarray, label: str) -> tuple[np.ndarray, np.ndarray]:
        """Per row of ``values`` (grid then guard variables): rescued after every kick, and its obs."""
        sim = self.pool.sim
        xs = [self.domain.to_plant(v, sim) for v in values]
        items = [(x, k) for x in xs for k in self.kicks]
        results = self._outcomes(items, label)
        self.simulations += len(items)
        ok = np.array([r[0] for r in results], dtype=bool).reshape(len(xs), len(self.kicks))
        obs = np.array([r[1] for r in results[:: len(self.kicks)]])
        return np.asarray(ok.all(axis=1)), obs

    def _outcomes(self, items: list[Start], label: str) -> list[Outcome]:
        """The outcome of each start: from the journal where it has one, else simulated (and kept)."""
        task = functools.partial(_rescued, steps=self.steps, core=self.core, grounded=self.grounded)
        n = max(len(items), 1)
        if self.journal is None:
            return self.pool.run(task, items, tick=lambda i: self.report(label, i / n)).results
        found: list[Outcome | None] = [self.journal.get(item) for item in items]
        todo = [i for i, f in enumerate(found) if f is None]
        self.reused += len(items) - len(todo)
        for first in range(0, len(todo), CHUNK):
            chunk = todo[first : first + CHUNK]
            tick = functools.partial(self._tick, label, len(items) - len(todo) + first, n)
            batch = self.pool.run(task, [items[i] for i in chunk], tick=tick)
            self.journal.record([items[i] for i in chunk], batch.results)
            for i, outcome in zip(chunk, batch.results, strict=True):
                found[i] = outcome
        return [f for f in found if f is not None]

    def _tick(self, label: str, before: int, n: int, done: int) -> None:
        """Progress of a chunk: ``done`` of its starts, after ``before`` of the ``n``."""
        self.report(label, (before + done) / n)

    def guard_values(self, n: int) -> np.ndarray:
        """``n`` guard draws, uniform in the guard box."""
        return self.rng.uniform(self.domain.guard_lo, self.domain.guard_hi, (n, len(self.domain.guard_vars)))


def _cell_points(grid: LookupGrid, cells: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One point per row of ``cells`` (cell indices), uniform in the cell."""
    return np.array(grid.lower) + (cells + rng.random(cells.shape)) * grid.widths


def _connected(table: np.ndarray, seed_cell: tuple[int, ...]) -> np.ndarray:
    """The marked cells connected (faces) to ``seed_cell``; empty if it is not marked."""
    if not table[seed_cell]:
        return np.zeros_like(table)
    labels, _ = ndimage.label(table)
    return labels == labels[seed_cell]


def _guard_corners(domain: _Domain) -> list[np.ndarray | None]:
    """The guard box's corners (at most 16, the first ones in order), or ``[None]`` without a guard."""
    if not domain.guard_vars:
        return [None]
    corners = itertools.product(*zip(domain.guard_lo, domain.guard_hi, strict=True))
    return [np.array(c) for c in itertools.islice(corners, 16)]


def _cell_slices(cells: tuple[int, ...], offset: tuple[int, ...]) -> tuple[slice, ...]:
    """The vertices at ``offset`` (0 or 1 per axis) from each cell, as slices of the vertex array."""
    return tuple(slice(o, o + c) for o, c in zip(offset, cells, strict=True))


def _probe_vertices(
    est: _Estimate, grid: LookupGrid, ok: np.ndarray, corner: np.ndarray | None
) -> np.ndarray:
    """``ok`` without the cells of which a vertex (with the guard at ``corner``) is not rescued."""
    offsets = list(itertools.product((0, 1), repeat=len(grid.cells)))
    need = np.zeros(tuple(c + 1 for c in grid.cells), dtype=bool)
    for off in offsets:
        need[_cell_slices(grid.cells, off)] |= ok
    idx = np.argwhere(need)
    pts = np.array(grid.lower) + idx * grid.widths
    guard = np.tile(corner, (len(idx), 1)) if corner is not None else est.guard_values(len(idx))
    rescued = np.zeros(need.shape, dtype=bool)
    rescued[tuple(idx.T)] = est.rescued(np.hstack([pts, guard]), f"probing {len(idx):,} vertices")[0]
    out = ok.copy()
    for off in offsets:
        out &= rescued[_cell_slices(grid.cells, off)]
    return out


def _probe(est: _Estimate, grid: LookupGrid) -> np.ndarray:
    """Mark the cells whose probes are all rescued.

    Probes: every vertex of the cell with the guard at each corner of its box (where the cart is
    far out and moving further; a vertex is shared by up to ``2**k`` cells and simulated once per
    corner), then ``probes`` random points in the cell with random guard values. A cell is dropped
    at its first failed probe.
    """
    ok = np.ones(grid.cells, dtype=bool)
    for corner in _guard_corners(est.domain):
        ok = _probe_vertices(est, grid, ok, corner)
    cells = np.argwhere(np.ones(grid.cells, dtype=bool))
    flat = ok.reshape(-1)
    for p in range(est.settings.probes):
        live = np.flatnonzero(flat)
        pts = _cell_points(grid, cells[live], est.rng)
        label = f"probing {len(live):,} cells ({p + 1}/{est.settings.probes})"
        flat[live] = est.rescued(np.hstack([pts, est.guard_values(len(live))]), label)[0]
    return flat.reshape(grid.cells)


def _draw_inside(grid: LookupGrid, est: _Estimate, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` states uniform in the region: (their cells, grid then guard values)."""
    marked = np.argwhere(grid.table)
    cells = marked[est.rng.integers(0, len(marked), n)]
    pts = _cell_points(grid, cells, est.rng)
    return cells, np.hstack([pts, est.guard_values(n)])


def _unmark(grid: LookupGrid, failed: np.ndarray) -> np.ndarray:
    """The table without the failed cells and the edge cells (depth 1) next to them."""
    table = grid.table.copy()
    edge = grid.depth() == 1
    for c in failed:
        lo = np.maximum(c - 1, 0)
        hi = np.minimum(c + 2, grid.cells)
        window = tuple(slice(int(a), int(b)) for a, b in zip(lo, hi, strict=True))
        table[window] &= ~edge[window]
        table[tuple(c)] = False
    return table


def _validate(est: _Estimate, grid: LookupGrid, seed_cell: tuple[int, ...]) -> tuple[LookupGrid, int, int]:
    """Fresh draws until one has no failure; a failure unmarks its cell. Returns (grid, rounds, unmarked)."""
    n = est.settings.validation
    unmarked = 0
    for rounds in range(1, MAX_ROUNDS + 1):
        cells, values = _draw_inside(grid, est, n)
        ok, _ = est.rescued(values, f"validation draw {rounds}: {n:,} fresh states in the region")
        if ok.all():
            return grid, rounds, unmarked
        table = _unmark(grid, cells[~ok])
        table = _connected(table, seed_cell)
        unmarked += int(grid.table.sum() - table.sum())
        if not table.any():
            break
        grid = replace(grid, table=table)
    raise RegionError(
        f"no rescue region validated for {est.pool.sim.coach.spec.name}: failures persist after "
        f"{MAX_ROUNDS} fresh draws of {n:,} states"
    )


def _coverage(est: _Estimate, grid: LookupGrid, spec: CoachSpec, card: ModelCard) -> Coverage:
    """Rescuable states over the domain, and how many the region, the core and the box hold."""
    d = est.domain
    n = est.settings.coverage
    pts = est.rng.uniform(d.lower, d.upper, (n, len(d.grid_vars)))
    ok, obs = est.rescued(np.hstack([pts, est.guard_values(n)]), f"coverage: {n:,} fresh states")
    names = card.observation_names
    regions: dict[str, Any] = {"rescue": GridRegion(grid, names)}  # the object the wrapper asks
    b = spec.bounds or {}
    if "ellipsoid" in b:
        regions["core"] = EllipsoidRegion(b["ellipsoid"], names, certified=True)
        regions["takeover ellipsoid"] = EllipsoidRegion(b["ellipsoid"], names)
    if "box" in b:
        regions["takeover box"] = region_from_bounds(b, names, "box")
    inside = {name: np.array([r.contains(o) for o in obs], dtype=bool) for name, r in regions.items()}
    contained = {k: int(np.sum(v & ok)) for k, v in inside.items()}
    volume = {k: float(np.mean(v)) for k, v in inside.items()}
    return Coverage(n, int(ok.sum()), contained, volume)


def _kicks(settings: RescueSettings, vertices: np.ndarray, fraction: float) -> list[np.ndarray | None]:
    """The agent steps every probe takes first (none for the predictive trigger)."""
    if settings.trigger == "predictive":
        return [None]
    return [v * fraction for v in vertices]


def _choose_fraction(
    est: _Estimate, grid: LookupGrid, vertices: np.ndarray, seed_cell: tuple[int, ...]
) -> float:
    """The full range if the coach rescues the operating point's cell after it, else the largest fraction."""
    centre = np.array(grid.lower) + (np.array([seed_cell]) + 0.5) * grid.widths
    guard = np.array([(est.domain.guard_lo + est.domain.guard_hi) / 2])

    def handled(f: float) -> bool:
        est.kicks = _kicks(est.settings, vertices, f)
        return bool(est.rescued(np.hstack([centre, guard]), f"action fraction {f:.3f}")[0][0])

    if handled(1.0):
        return 1.0
    f = halving_bisect(handled, 10)
    if f <= 0.0:
        raise RegionError(
            f"{est.pool.sim.coach.spec.name}: the coach cannot rescue the operating point after any "
            "agent step"
        )
    return f


def _check_settings(s: RescueSettings) -> None:
    """One-line :class:`RegionError` on settings out of range, naming the field (its ``param``).

    :class:`RescueSettings` calls it whenever one is made (``replace`` included), so settings out of
    range are refused where they are given, before any work (or progress bar) starts.
    """
    if s.trigger not in TRIGGERS:
        expected = f"expected one of {', '.join(TRIGGERS)}"
        raise RegionError(f"trigger={shown(s.trigger)}: {expected}", param="trigger")
    if s.action_fraction is not None and not (s.trigger == "predictive" and s.action_fraction == 0.0):
        number(s.action_fraction, "action_fraction", RegionError, low=0.0, high=1.0, low_open=True,
               param="action_fraction")  # fmt: skip
    grid = (s.variables, s.half_range, s.cells)
    k = len(s.variables) if isinstance(s.variables, (tuple, list)) else 0
    if not 1 <= k <= 4 or not all(isinstance(g, (tuple, list)) and len(g) == k for g in grid):
        raise RegionError("rescue grid: expected 1 to 4 variables, with a half-range and a cell count each")
    for c in s.cells:
        integer(c, "cells", RegionError, low=2, high=400)
    if not isinstance(s.guard, dict):
        expected = "expected a table of variable -> half-width"
        raise RegionError(f"guard={shown(s.guard)}: {expected}", param="guard")
    for h in (*s.half_range, *s.guard.values()):
        number(h, "half-range", RegionError, low=0.0, low_open=True)
    for name, high in (("probes", 100), ("validation", 10**6), ("coverage", 10**6)):
        integer(getattr(s, name), name, RegionError, low=1, high=high, param=name)
    number(s.horizon_s, "horizon_s", RegionError, low=0.0, low_open=True, high=60.0, unit="s",
           param="horizon_s")  # fmt: skip
    check_seed(s.seed, "seed", RegionError, param="seed")


@contextlib.contextmanager
def simulations(
    spec: CoachSpec,
    loaded: LoadedModel,
    settings: Any,
    domain_of: Callable[[ModelCard, LoadedModel, np.ndarray], _Domain],
    workers: int | None,
    progress: Progress | None = None,
    journal: str | Path | None = None,
    into: str = "core",
) -> Iterator[tuple[_Estimate, Coach, Linearization]]:
    """The rescue simulations' setting, with its worker pool open: the estimate, the coach, its linearization.

    ``settings`` needs ``horizon_s`` and ``seed`` (a :class:`RescueSettings`, or a classifier's
    settings); ``domain_of(card, loaded, y_op)`` lays out the states the simulations start from.
    Draws nothing: the estimate's random stream starts at ``settings.seed`` for its first user.
    ``journal``: a folder that keeps every outcome as it is found (in a subfolder named by
    :func:`outcome_facts`' digest), so that the same estimate run again simulates only what it
    lacks (:mod:`pidlab.region.journal`); None keeps nothing. ``into``: where a rescue ends
    (:data:`RESCUE_ENDS`, :func:`_core`).
    """
    from pidlab.controller.analysis import analyze_coach

    card = loaded.require_card()
    coach = Coach(spec, loaded)
    lin = analyze_coach(coach, loaded).linearization
    with SimulationPool(spec, loaded, lin, resolve_workers(workers, RegionError)) as pool:
        est = _Estimate(
            pool, domain_of(card, loaded, pool.sim.y_op), settings, [None],
            horizon_steps(settings.horizon_s, loaded.control_dt), _core(spec, card, into),
            np.random.default_rng(settings.seed), progress or (lambda stage, f: None),
            grounded=pool.sim.ground is not None,
        )  # fmt: skip
        if journal is not None:
            facts = outcome_facts(spec, loaded, est.steps, est.grounded, into)
            est.journal = LabelJournal(Path(journal) / journal_key(facts))
        yield est, coach, lin


def outcome_facts(
    spec: CoachSpec, loaded: LoadedModel, steps: int, grounded: bool, into: str = "core"
) -> dict[str, Any]:
    """What decides a rescue's outcome besides its start.

    The coach's law, its certified core, the env, the compiled model and its card
    (:func:`pidlab.plant.model.model_digest`: an edited MJCF file is another model), the horizon
    (control steps), starts on the floor, where a rescue ends, and the versions that simulate it.
    """
    import gymnasium

    core = {k: v for k, v in (spec.bounds or {}).items() if k in ("ellipsoid", "box")}
    return {
        "env": spec.env_id, "law": law_digest(spec), "core": core, "model": model_digest(loaded),
        "steps": steps, "grounded": grounded, "into": into, "pidlab": __version__,
        "mujoco": mujoco.__version__, "gymnasium": gymnasium.__version__,
    }  # fmt: skip


@contextlib.contextmanager
def _estimating(
    spec: CoachSpec,
    loaded: LoadedModel,
    settings: RescueSettings,
    workers: int | None,
    progress: Progress | None = None,
    journal: str | Path | None = None,
) -> Iterator[tuple[_Estimate, Coach, Linearization]]:
    """:func:`simulations` over the grid and guard domain of ``settings`` (checked first)."""
    _check_settings(settings)
    domain_of = functools.partial(_domain, settings)
    with simulations(spec, loaded, settings, domain_of, workers, progress, journal) as found:
        yield found


def estimate_rescue(
    spec: CoachSpec,
    loaded: LoadedModel,
    settings: RescueSettings | None = None,
    workers: int | None = None,
    progress: Progress | None = None,
    journal: str | Path | None = None,
) -> RescueRegion:
    """Estimate, validate and score the coach's rescue region (see the module docstring).

    Parameters
    ----------
    spec : CoachSpec
        The coach, with its certified core in ``[bounds]`` (``pidlab bounds``): where a rescue ends.
        Its other ``[bounds]`` sets are scored on the coverage draw too.
    loaded : LoadedModel
        The model of ``spec.env_id``, with a model card.
    settings : RescueSettings, optional
        Default: :func:`default_settings`.
    workers : int, optional
        Worker processes for the simulations; the result is the same for any number.
    progress : callable, optional
        ``progress(stage, fraction)``.
    journal : path, optional
        A folder that keeps every simulation's outcome as it is found, so that the same estimate run
        again after a stop simulates only what it lacks and gives the same region
        (:mod:`pidlab.region.journal`). None keeps nothing.

    Raises
    ------
    RegionError
        Settings out of range, a variable that cannot be set, a spec without a certified core, a
        coach that rescues nothing, or a journal path that is a file.
    """
    instance(spec, CoachSpec, "spec")
    instance(loaded, LoadedModel, "loaded")
    if settings is not None:
        instance(settings, RescueSettings, "settings")
    t0 = time.perf_counter()
    s = settings if settings is not None else default_settings(spec, loaded)
    with _estimating(spec, loaded, s, workers, progress, journal) as (est, coach, lin):
        vertices = _action_vertices(coach, lin)
        if len(vertices) > MAX_VERTICES:
            vertices = vertices[est.rng.choice(len(vertices), MAX_VERTICES, replace=False)]
        domain = est.domain
        guard = {v: (float(lo), float(hi)) for v, lo, hi in zip(*domain.guard_box(), strict=True)}
        blank = LookupGrid(
            domain.grid_vars, tuple(domain.lower), tuple(domain.upper), tuple(s.cells),
            np.zeros(s.cells, dtype=bool), guard, s.trigger, 0.0,
        )  # fmt: skip
        seed_cell = tuple(int(c) for c in blank.cell_of(np.array([(domain.lower + domain.upper) / 2]))[0])
        fraction = 0.0
        if s.trigger == "reactive":
            fraction = s.action_fraction or _choose_fraction(est, blank, vertices, seed_cell)
            est.kicks = _kicks(s, vertices, fraction)
        table = _connected(_probe(est, blank), seed_cell)
        if not table.any():
            raise RegionError(f"{spec.name}: the coach rescues no cell around the operating point")
        grid = replace(blank, table=table, action_fraction=fraction)
        grid, rounds, unmarked = _validate(est, grid, seed_cell)
        coverage = _coverage(est, grid, spec, loaded.require_card())
    used = replace(s, action_fraction=fraction if s.trigger == "reactive" else 0.0)
    elapsed = time.perf_counter() - t0
    prov = _provenance(used, (s.validation, rounds, unmarked), coverage, est.simulations, elapsed)
    prov["fraction_chosen"] = s.trigger == "reactive" and s.action_fraction is None
    if est.grounded:
        prov["starts"] = STARTS_ON_FLOOR
    return RescueRegion(
        spec.env_id, spec.name, grid, used, (s.validation, 0), rounds, unmarked, coverage, elapsed, prov,
        reused=est.reused,
    )


def _provenance(
    s: RescueSettings, checks: tuple[int, int, int], cov: Coverage, simulations: int, elapsed: float
) -> dict[str, Any]:
    """The region's ``[bounds.rescue.provenance]`` table."""
    import datetime as _dt

    validation, rounds, unmarked = checks
    out: dict[str, Any] = {
        "method": "simulation: lookup grid, every probe rescued, validated on fresh states",
        "horizon_s": float(s.horizon_s),
        "probing": "every cell vertex at every guard corner, then random points",
        "probes_per_cell": int(s.probes),
        "validation_samples": int(validation),
        "validation_failures": 0,
        "failure_probability_95": 3.0 / validation,
        "validation_rounds": int(rounds),
        "cells_unmarked_by_validation": int(unmarked),
        "coverage_samples": int(cov.samples),
        "coverage_rescuable": int(cov.rescuable),
        "simulations": int(simulations),
        "elapsed_s": round(float(elapsed), 1),
        "seed": int(s.seed),
        "date": _dt.date.today().isoformat(),
        "pidlab_version": __version__,
    }
    for name in cov.contained:
        key = name.replace(" ", "_")
        out[f"coverage_{key}"] = cov.fraction(name)
        out[f"volume_{key}"] = cov.volume[name]
    return out


def default_settings(spec: CoachSpec, loaded: LoadedModel, trigger: str = "predictive") -> RescueSettings:
    """The model card's ``[rescue]`` settings, or the core loop's signal and rate over a default domain.

    Without a card table: the grid spans the signal's termination limit (or 0.5) and ten times that
    per second for its rate, 40 x 40 cells, no guard.
    """
    card = loaded.require_card()
    if card.rescue is not None:
        r = card.rescue
        return RescueSettings(r.variables, r.half_range, r.cells, dict(r.guard), trigger)
    lp = spec.loops[0]
    if lp.rate_signal is None:
        raise RegionError(f"{spec.name}: its first loop has no rate signal; give the grid's variables")
    limits = [min(abs(t.low), abs(t.high)) for t in card.termination if t.signal == lp.signal]
    half = limits[0] if limits else 0.5
    return RescueSettings((lp.signal, lp.rate_signal), (half, 10.0 * half), (40, 40), {}, trigger)


def with_rescue(spec: CoachSpec, region: RescueRegion, takeover: bool = True) -> CoachSpec:
    """A copy of ``spec`` whose ``[bounds]`` holds ``region`` (as its takeover region if ``takeover``).

    A ``[bounds.forecast]`` measured on the region it replaces is dropped.
    """
    instance(spec, CoachSpec, "spec")
    instance(region, RescueRegion, "region")
    b = dict(spec.bounds or {})
    b["rescue"] = region.to_table()
    b.pop("forecast", None)  # measured on the region it replaces
    if takeover:
        b["takeover"] = "rescue"
    else:
        b.pop("takeover", None)
    return replace(spec, bounds=b)


def rescued_fraction(
    spec: CoachSpec,
    loaded: LoadedModel,
    settings: RescueSettings,
    samples: int,
    workers: int | None = None,
) -> float:
    """Share of ``samples`` states, uniform over the settings' domain (grid and guard), the coach rescues.

    The states come from ``settings.seed`` alone, so every coach is scored on the same ones (the
    predictive reading: no agent step first). The room tuner's objective.
    """
    _check_settings(settings)
    integer(samples, "samples", RegionError, low=1, high=10**6)
    with _estimating(spec, loaded, settings, workers) as (est, _, _):
        d = est.domain
        pts = est.rng.uniform(d.lower, d.upper, (samples, len(d.grid_vars)))
        ok, _ = est.rescued(np.hstack([pts, est.guard_values(samples)]), "scoring")
    return float(np.mean(ok))
