"""A look-ahead without a copy of the simulator: the next observation from the discrete linear model.

The predictive trigger (:class:`pidlab.rl.predict.Predictor`) asks where the agent's action would
take the env, and answers on an exact copy of the MuJoCo state: an oracle a real robot has not.
:class:`LinearForecast` answers from the env's discrete linear model instead (the one
:func:`pidlab.linear.linearize.linearize` builds at the card's operating point, at the control
period): from the current joint state ``(qpos, qvel, act)`` and the action,

    x' = Ad (x - x_op) + Bd (u - u_op)

in tangent coordinates, mapped to the observation variables through the model card. Only the
variables read from ``qpos`` or ``qvel`` can be forecast (a constraint force cannot).

The forecast is wrong by some amount. :class:`ForecastError` is that amount per region variable,
measured on recorded transitions (:func:`pidlab.rl.calibrate.measure_forecast`), and
:func:`margin_region` asks the rescue region about the whole box of that size about a forecast
(:class:`MarginRegion` for a lookup grid, :class:`ClassifierMarginRegion` for a classifier, which
bounds the network's score over the box): when every state within the error of the forecast is
inside the region, the rescue region's guarantee holds for the real next state whenever the error
holds. A spec keeps the measurement
in its ``[bounds.forecast]`` table, with the digest of the rescue region it was measured on; a
forecast of another region is refused.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from pidlab.errors import CoachingError, SpecError
from pidlab.lookup import (
    BOUNDS,
    MAX_PIECES,
    SPLITS,
    ForecastError,
    MarginScale,
    RescueClassifier,
    ResidualNet,
    parse_forecast,
    region_digest,
    valid_pieces,
)  # fmt: skip
from pidlab.plant.card import ModelCard
from pidlab.plant.observation import variable_address
from pidlab.region.relaxation import lowest_scores
from pidlab.region.takeover import ClassifierRegion, GridRegion, checked_observation, observation_indices

SOURCES = ("qpos", "qvel")
"""The observation sources a forecast of the joint state can give."""


@dataclass(frozen=True)
class LinearForecast:
    """The discrete linear model of an env, read as a one-step forecast of its observation.

    Attributes
    ----------
    Ad, Bd : ndarray
        Discrete state and input matrices at the control period (states ``(dq, dqvel, dact)`` in
        tangent coordinates about the operating point, inputs ``ctrl - ctrl_op``).
    qpos_op, qvel_op, act_op, ctrl_op : ndarray
        The operating point.
    ctrl_low, ctrl_high : ndarray
        Where MuJoCo clamps each control (``-inf, inf`` for an unlimited actuator).
    columns : tuple of (int, str, int, str or None, tuple or None)
        Per observation variable that can be forecast: its column in the observation, its source
        (``qpos``/``qvel``), its address there, its transform and its clip.
    size : int
        The observation's length.
    blind : tuple of int
        The inputs (:meth:`inputs`) a learned network must not read (:func:`blind_inputs`).
    """

    Ad: np.ndarray
    Bd: np.ndarray
    qpos_op: np.ndarray
    qvel_op: np.ndarray
    act_op: np.ndarray
    ctrl_op: np.ndarray
    ctrl_low: np.ndarray
    ctrl_high: np.ndarray
    columns: tuple[tuple[int, str, int, str | None, tuple[float, float] | None], ...]
    size: int
    blind: tuple[int, ...] = ()

    @property
    def variables(self) -> tuple[int, ...]:
        """Columns of the observation the forecast fills (the others are NaN)."""
        return tuple(c[0] for c in self.columns)

    def state(self, model: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray, act: np.ndarray) -> np.ndarray:
        """Tangent-space deviation ``x - x_op`` of a joint state, shape ``(2 nv + na,)``."""
        dq = np.zeros(model.nv)
        mujoco.mj_differentiatePos(model, dq, 1.0, self.qpos_op, np.asarray(qpos, dtype=float))
        return np.concatenate([dq, np.asarray(qvel, dtype=float) - self.qvel_op,
                               np.asarray(act, dtype=float) - self.act_op])  # fmt: skip

    def observation(
        self, model: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray, act: np.ndarray, action: np.ndarray
    ) -> np.ndarray:
        """The forecast observation one control period after ``action`` from ``(qpos, qvel, act)``.

        NaN in the columns the forecast cannot fill (sources other than ``qpos`` and ``qvel``).
        """
        return self.from_inputs(model, self.inputs(model, qpos, qvel, act, action))

    def from_inputs(self, model: mujoco.MjModel, z: np.ndarray) -> np.ndarray:
        """:meth:`observation` from the linear model's inputs ``z`` (:meth:`inputs`)."""
        n = self.Ad.shape[0]
        x = self.Ad @ z[:n] + self.Bd @ z[n:]
        nv = model.nv
        q = self.qpos_op.copy()
        mujoco.mj_integratePos(model, q, x[:nv], 1.0)
        values = {"qpos": q, "qvel": self.qvel_op + x[nv : 2 * nv]}
        out = np.full(self.size, np.nan)
        for col, source, address, transform, clip in self.columns:
            v = float(values[source][address])
            if transform == "sin":
                v = float(np.sin(v))
            elif transform == "cos":
                v = float(np.cos(v))
            if clip is not None:
                v = min(max(v, clip[0]), clip[1])
            out[col] = v
        return out


    def inputs(
        self, model: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray, act: np.ndarray, action: np.ndarray
    ) -> np.ndarray:
        """The linear model's inputs: the state's tangent-space deviation, then the clamped control's."""
        u = np.clip(np.asarray(action, dtype=float).reshape(-1), self.ctrl_low, self.ctrl_high) - self.ctrl_op
        return np.concatenate([self.state(model, qpos, qvel, act), u])

    def observed_inputs(self, model: mujoco.MjModel, obs: np.ndarray) -> np.ndarray:
        """The inputs of a forecast made from each observation row, with the operating point's control.

        The joint state is the operating point's, with every position and velocity the observation
        reads set from it (an angle from its sine, or from its cosine when the sine is not observed);
        the control's deviation is 0. Used where margins are asked of a state, not of a forecast
        (coverage, the share of a region kept).
        """
        rows = np.atleast_2d(np.asarray(obs, dtype=float))
        out = np.empty((len(rows), self.Ad.shape[0] + self.Bd.shape[1]))
        order = sorted(self.columns, key=lambda c: c[3] == "sin")  # a sine overrides a cosine
        for r, row in enumerate(rows):
            q, v = self.qpos_op.copy(), self.qvel_op.copy()
            for col, source, address, transform, _ in order:
                (q if source == "qpos" else v)[address] = _angle(float(row[col]), transform)
            out[r] = np.concatenate([self.state(model, q, v, self.act_op), np.zeros(self.Bd.shape[1])])
        return out


@dataclass(frozen=True)
class LearnedForecast:
    """The linear forecast corrected by a learned network (:class:`~pidlab.lookup.ResidualNet`).

    The network adds its correction to the linear forecast of the variables it was fitted for (each
    clipped again as the card clips it); every other column is the linear forecast's.

    Attributes
    ----------
    linear : LinearForecast
    network : ResidualNet
    corrected : tuple of (int, tuple or None)
        Per corrected variable, its column in the observation and its clip.
    """

    linear: LinearForecast
    network: ResidualNet
    corrected: tuple[tuple[int, tuple[float, float] | None], ...]

    @property
    def variables(self) -> tuple[int, ...]:
        """Columns of the observation the forecast fills (the others are NaN)."""
        return self.linear.variables

    def observation(
        self, model: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray, act: np.ndarray, action: np.ndarray
    ) -> np.ndarray:
        """The corrected forecast observation one control period after ``action``."""
        return self.from_inputs(model, self.inputs(model, qpos, qvel, act, action))

    def inputs(
        self, model: mujoco.MjModel, qpos: np.ndarray, qvel: np.ndarray, act: np.ndarray, action: np.ndarray
    ) -> np.ndarray:
        """The linear model's inputs (:meth:`LinearForecast.inputs`)."""
        return self.linear.inputs(model, qpos, qvel, act, action)

    def from_inputs(self, model: mujoco.MjModel, z: np.ndarray) -> np.ndarray:
        """:meth:`observation` from the linear model's inputs ``z``."""
        return self.correct(self.linear.from_inputs(model, z)[None, :], z[None, :])[0]

    def correct(self, linear: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        """Linear forecasts (rows of ``linear``) corrected by the network at their ``inputs``."""
        out = np.array(linear, dtype=float)
        fix = self.network.correction(inputs)
        for k, (col, clip) in enumerate(self.corrected):
            v = out[:, col] + fix[:, k]
            out[:, col] = np.clip(v, clip[0], clip[1]) if clip is not None else v
        return out


def check_network(linear: LinearForecast, network: ResidualNet, what: str) -> None:
    """Refuse a network fitted on other inputs than this env's linear model gives (or blinds).

    Raises
    ------
    CoachingError
        Another number of inputs, or other blind inputs (:func:`blind_inputs`).
    """
    k = linear.Ad.shape[0] + linear.Bd.shape[1]
    if network.inputs != k:
        raise CoachingError(
            f"{what} takes {network.inputs} inputs, and this env's linear model has {k} "
            "(states and controls): it was fitted for another model; run `pidlab forecast SPEC` again"
        )
    if network.blind != linear.blind:
        raise CoachingError(
            f"{what} reads inputs {list(network.blind)} as blind, and this env's are "
            f"{list(linear.blind)} (the positions its observation leaves out, which the dynamics do not "
            "depend on and which grow as the robot moves: a network that reads them answers for a robot "
            "that has moved away with figures its margins never measured); run `pidlab forecast SPEC` again"
        )


def learned_forecast(linear: LinearForecast, network: ResidualNet, card: ModelCard) -> LearnedForecast:
    """The linear forecast with ``network``'s correction, checked against the card and the linear model.

    Raises
    ------
    CoachingError
        The network takes another number of inputs than the linear model has, or corrects a
        variable the forecast does not give.
    """
    check_network(linear, network, "the learned forecast")
    names = [v.name for v in card.observation]
    clips = {c[0]: c[4] for c in linear.columns}
    corrected = []
    for v in network.variables:
        col = names.index(v) if v in names else None
        if col is None or col not in clips:
            raise CoachingError(
                f"the learned forecast corrects {v!r}, which no joint-state forecast gives here"
            )
        corrected.append((col, clips[col]))
    return LearnedForecast(linear, network, tuple(corrected))


def forecastable(card: ModelCard) -> tuple[str, ...]:
    """The card's observation variables a forecast of the joint state gives (read from qpos or qvel)."""
    return tuple(v.name for v in card.observation if v.source in SOURCES)


def check_forecastable(card: ModelCard, variables: tuple[str, ...] | list[str], where: str) -> None:
    """Refuse a region over a variable that no joint-state forecast gives.

    Raises
    ------
    CoachingError
        Naming the variable and its source.
    """
    can = forecastable(card)
    sources = {v.name: v.source for v in card.observation}
    for name in variables:
        if name not in can:
            raise CoachingError(
                f"{where}: the region tests {name!r}, read from {sources.get(name, '?')}; "
                "the model predictor "
                f"forecasts only variables read from qpos or qvel ({', '.join(can) or 'none here'}); "
                "use predictor = 'exact'"
            )


def _angle(x: float, transform: str | None) -> float:
    """The coordinate an observed value reads: an angle from its sine or cosine, else the value."""
    if transform == "sin":
        return float(np.arcsin(np.clip(x, -1.0, 1.0)))
    if transform == "cos":
        return float(np.arccos(np.clip(x, -1.0, 1.0)))
    return x


def blind_inputs(card: ModelCard, model: mujoco.MjModel) -> tuple[int, ...]:
    """The linear model's inputs a learned network must not read: positions the observation leaves out.

    A joint whose position no observation variable reads (Gymnasium's walkers leave out the forward
    position ``rootx``: the dynamics do not depend on it) has its tangent-space position entries
    here. Such a coordinate grows without bound as the robot moves, far past the values the network
    was fitted and its margins measured on; zeroed, it cannot move the correction.
    """
    seen = {v.joint for v in card.observation if v.source == "qpos"}
    out: list[int] = []
    for j in range(model.njnt):
        if mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j) in seen:
            continue
        end = int(model.jnt_dofadr[j + 1]) if j + 1 < model.njnt else model.nv
        out.extend(range(int(model.jnt_dofadr[j]), end))
    return tuple(out)


def linear_forecast(lin: Any, card: ModelCard, model: mujoco.MjModel) -> LinearForecast:
    """The forecast of a :class:`~pidlab.linear.linearize.Linearization` (``discretization="step"``).

    Raises
    ------
    CoachingError
        The linearization's discrete model is not at the env's control period.
    """
    if lin.frame_skip < 1 or not np.isfinite(lin.Ad).all() or not np.isfinite(lin.Bd).all():
        raise CoachingError(
            f"{lin.source}: the linear model is not finite; the model predictor cannot use it"
        )
    op = lin.op
    limited = np.asarray(model.actuator_ctrllimited, dtype=bool)
    rng = np.asarray(model.actuator_ctrlrange, dtype=float).reshape(-1, 2)
    low = np.where(limited, rng[:, 0], -np.inf)
    high = np.where(limited, rng[:, 1], np.inf)
    columns = tuple(
        (i, v.source, variable_address(model, v), v.transform,
         (float(v.clip[0]), float(v.clip[1])) if v.clip is not None else None)
        for i, v in enumerate(card.observation)
        if v.source in SOURCES
    )  # fmt: skip
    act = np.asarray(getattr(op, "act", np.zeros(model.na)), dtype=float).reshape(-1)
    return LinearForecast(
        Ad=np.asarray(lin.Ad, dtype=float), Bd=np.asarray(lin.Bd, dtype=float),
        qpos_op=np.asarray(op.qpos, dtype=float), qvel_op=np.asarray(op.qvel, dtype=float),
        act_op=act if act.size == model.na else np.zeros(model.na), ctrl_op=np.asarray(op.ctrl, dtype=float),
        ctrl_low=low, ctrl_high=high, columns=columns, size=len(card.observation),
        blind=blind_inputs(card, model),
    )  # fmt: skip


# ----------------------------------------------------------------------------- the error and the region


def spec_forecast(bounds: dict[str, Any] | None, name: str) -> ForecastError:
    """The forecast measurement of a spec's ``[bounds]``, checked against its rescue region.

    Raises
    ------
    CoachingError
        No ``[bounds.forecast]``, or one measured on another rescue region, or one that misses a
        variable the region tests.
    """
    b = bounds or {}
    if "forecast" not in b:
        raise CoachingError(
            f"{name}: predictor 'model', but the spec has no [bounds.forecast] "
            "(the forecast's measured error); "
            "run `pidlab forecast SPEC --write`"
        )
    try:
        forecast = parse_forecast(b["forecast"])
    except SpecError as exc:
        raise CoachingError(f"{name}: {exc}") from None
    rescue = b.get("rescue")
    if rescue is None or forecast.region != region_digest(rescue):
        raise CoachingError(
            f"{name}: [bounds.forecast] was measured on another rescue region (region {forecast.region}); "
            "run `pidlab forecast SPEC --write` again"
        )
    tested = (*rescue.get("variables", ()), *rescue.get("guard", {}))
    missing = [v for v in tested if v not in forecast.margin]
    if missing:
        raise CoachingError(
            f"{name}: [bounds.forecast] has no margin for {', '.join(missing)}, which the region tests"
        )
    return forecast


class MarginRegion(GridRegion):
    """The rescue region asked of a forecast: whether every state within its margins is inside.

    A forecast ``g`` passes when the box ``[g - m, g + m]`` (``m`` the forecast's margins) lies in
    the guard and touches only marked cells of the grid. Then the true next state, wherever it
    lies within the margins of the forecast, is in the rescue region, and the region's guarantee
    holds for it. The box is tested as it is, not rounded to whole cells: a margin far below a
    cell's width costs only the points that near a cell's unmarked neighbour. The hand-back
    (:meth:`inner`) is the rescue region's own: it is asked of real states.

    Parameters
    ----------
    region : GridRegion
        The rescue region (its observation layout).
    margins : dict
        ``variable -> margin`` for every grid and guard variable.

    Raises
    ------
    CoachingError
        A guard range or a grid axis is no wider than twice its margin (no box fits).
    """

    def __init__(self, region: GridRegion, margins: dict[str, float]) -> None:
        grid = region.grid
        super().__init__(grid, region.observation_names)
        self.margins = {v: float(margins[v]) for v in (*grid.variables, *grid.guard)}
        names = region.observation_names
        self._boxes = []
        for k, v in enumerate(grid.variables):
            lo, hi, m = grid.lower[k], grid.upper[k], self.margins[v]
            _check_room(v, m, lo, hi)
            self._boxes.append((names.index(v), lo, hi, float(grid.widths[k]), grid.cells[k], m))
        self._guard = []
        for v, (lo, hi) in grid.guard.items():
            m = self.margins[v]
            _check_room(v, m, lo, hi)
            self._guard.append((names.index(v), lo + m, hi - m))
        self._table = np.asarray(grid.table, dtype=bool)

    def _contains(self, obs: np.ndarray) -> bool:
        if not self._in_guard(obs):
            return False
        cells = []
        for i, lo, hi, width, n, m in self._boxes:
            a, b = float(obs[i]) - m, float(obs[i]) + m
            if not (lo <= a and b <= hi):  # also False for NaN
                return False
            cells.append(slice(min(int((a - lo) / width), n - 1), min(int((b - lo) / width), n - 1) + 1))
        return bool(self._table[tuple(cells)].all())


def box_in_classifier(
    classifier: RescueClassifier, centre: np.ndarray, margins: np.ndarray, threshold: float,
    splits: int = SPLITS, bound: str = "interval", pieces: int | None = None,
) -> bool:  # fmt: skip
    """Whether every state of the box ``centre +- margins`` scores at least ``threshold``.

    :func:`pidlab.region.relaxation.lowest_scores` bounds the score over a box from below
    (interval arithmetic; with ``bound = "linear"``, for a box that leaves open, also the linear
    relaxation); where the bound falls short, the box is halved along its widest side (in the
    network's scaled units) and each half asked again, ``splits`` times at most. A box any of whose
    pieces' centres scores below the threshold fails at once (that state is outside); one still
    unproven after the last halving fails too, and so does one whose next halving would ask more
    than ``pieces`` boxes at once: that caps a query's work at fewer than ``2 * pieces`` bounded
    boxes, whatever the box (None: no cap but ``splits``, at most ``2 ** (splits + 1) - 1``). So a True is
    proof (every state of the box is inside) and a False may be a box that is inside but too close
    to the edge to prove it. The domain box is not checked here.
    """
    c = np.atleast_2d(np.asarray(centre, dtype=float))
    m = np.asarray(margins, dtype=float)
    return bool(boxes_in_classifier(classifier, c, m, threshold, splits, bound, pieces)[0])


def boxes_in_classifier(
    classifier: RescueClassifier, centres: np.ndarray, margins: np.ndarray, threshold: float,
    splits: int = SPLITS, bound: str = "interval", pieces: int | None = None,
) -> np.ndarray:  # fmt: skip
    """:func:`box_in_classifier` of each row of ``centres`` (shape ``(n, k)``), all at once: bool ``(n,)``.

    ``margins``: shape ``(k,)`` (the same for every box) or ``(n, k)``. ``pieces`` caps each row's
    boxes at one halving, as for one box.
    """
    c = np.atleast_2d(np.asarray(centres, dtype=float))
    m = np.array(np.broadcast_to(np.asarray(margins, dtype=float), c.shape))
    owner = np.arange(len(c))
    failed = np.zeros(len(c), dtype=bool)
    width = np.array(classifier.upper) - np.array(classifier.lower)
    for level in range(splits + 1):
        failed[owner[classifier.scores(c) < threshold]] = True  # a state of the box is outside
        open_ = ~failed[owner]
        open_[open_] = ~_proven(classifier, c[open_], m[open_], threshold, bound)
        c, m, owner = c[open_], m[open_], owner[open_]
        if not len(c):
            break
        if level == splits:
            failed[owner] = True  # still unproven after the last halving
            break
        if pieces is not None:
            c, m, owner = _within(failed, c, m, owner, pieces)
            if not len(c):
                break
        rows = np.arange(len(m))
        side = np.argmax(m / width, axis=1)
        m[rows, side] /= 2.0
        step = np.zeros_like(m)
        step[rows, side] = m[rows, side]
        c, m, owner = np.concatenate([c - step, c + step]), np.concatenate([m, m]), np.tile(owner, 2)
    return ~failed


def _within(
    failed: np.ndarray, c: np.ndarray, m: np.ndarray, owner: np.ndarray, pieces: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The open boxes of the rows whose halving asks at most ``pieces`` boxes; the others fail."""
    over = 2 * np.bincount(owner, minlength=len(failed)) > pieces
    failed[over] = True
    keep = ~over[owner]
    return c[keep], m[keep], owner[keep]


def _proven(
    classifier: RescueClassifier, c: np.ndarray, m: np.ndarray, threshold: float, bound: str
) -> np.ndarray:
    """Whether a lower bound of the score over each box reaches ``threshold``.

    The interval bound, and with ``bound = "linear"`` the linear relaxation for the boxes the
    interval bound leaves open.
    """
    proven = lowest_scores(classifier, c, m) >= threshold
    if bound == "linear" and not proven.all():
        open_ = ~proven
        proven[open_] = lowest_scores(classifier, c[open_], m[open_], "linear") >= threshold
    return proven


class ClassifierMarginRegion:
    """A classifier rescue region asked of a forecast: whether every state within its margins is inside.

    A forecast ``g`` passes when the box ``[g - m, g + m]`` lies in the classifier's domain box and
    :func:`box_in_classifier` proves that every state in it scores at least the region's threshold.
    Then the true next state, wherever it lies within the margins of the forecast, is in the rescue
    region, and the region's guarantee holds for it. The hand-back (:meth:`inner`) is the rescue
    region's own: it is asked of real states.

    Parameters
    ----------
    region : ClassifierRegion
        The rescue region (its observation layout and threshold).
    margins : dict
        ``variable -> margin`` for every variable the classifier tests (with ``adaptive``, the
        largest: asked when a query comes without the forecast's inputs).
    bound : {"interval", "linear"}
        How the score is bounded over a box (:data:`pidlab.lookup.BOUNDS`, :func:`box_in_classifier`).
    pieces : int or None
        The most boxes one query bounds at one halving (:func:`box_in_classifier`); None: no cap.
    adaptive : MarginScale, optional
        Margins that depend on the forecast's inputs (:class:`pidlab.lookup.MarginScale`, over the
        variables of ``margins``, in its order): :meth:`contains` and :meth:`hold` take the inputs.

    Raises
    ------
    CoachingError
        A domain range no wider than twice its margin (no box fits), an unknown ``bound``, or
        ``pieces`` below 1.
    """

    kind = "rescue"
    trigger = "predictive"

    def __init__(
        self, region: ClassifierRegion, margins: dict[str, float], bound: str = "interval",
        pieces: int | None = None, adaptive: MarginScale | None = None,
    ) -> None:  # fmt: skip
        check_bound(bound)
        check_pieces(pieces)
        clf = region.classifier
        self.region = region
        self.bound = bound
        self.pieces = pieces
        self.classifier = clf
        self.variables = clf.variables
        self.observation_names = region.observation_names
        self.threshold = region.threshold
        self.scale = 1.0
        self.margins = {v: float(margins[v]) for v in clf.variables}
        self._m = np.array([self.margins[v] for v in clf.variables])
        for v, m, lo, hi in zip(clf.variables, self._m, clf.lower, clf.upper, strict=True):
            _check_room(v, float(m), lo, hi)
        names = region.observation_names
        self._idx = np.array(observation_indices(clf.variables, names, "bounds.rescue.variables"))
        self._lower, self._upper = np.array(clf.lower), np.array(clf.upper)
        self.adaptive = adaptive
        if adaptive is not None:
            order = list(margins)
            self._ceiling = np.array([float(margins[v]) for v in order])
            self._pick = np.array([order.index(v) for v in clf.variables])

    def contains(self, obs: np.ndarray, inputs: np.ndarray | None = None) -> bool:
        """Whether the box of the margins about ``obs`` lies in the region (proven, see the class).

        ``inputs``: the linear model's inputs the forecast ``obs`` was made from (adaptive margins;
        without them, the largest margins).

        Raises
        ------
        CoachingError
            ``obs`` is not an observation of the env (another length, not numbers).
        """
        return checked_observation(obs, len(self.observation_names), lambda o: self._contains(o, inputs))

    def _contains(self, obs: np.ndarray, inputs: np.ndarray | None = None) -> bool:
        y = np.asarray(obs, dtype=float)[self._idx]
        return bool(self.hold(y, None if inputs is None else np.atleast_2d(inputs))[0])

    def holds(self, y: np.ndarray) -> bool:
        """:meth:`contains` of the classifier's variables ``y`` alone (its order), at the largest margins."""
        return bool(self.hold(y)[0])

    def margins_of(self, n: int, inputs: np.ndarray | None = None) -> np.ndarray:
        """The margins of ``n`` queries (classifier order), shape ``(n, k)``: adaptive given ``inputs``."""
        if self.adaptive is None or inputs is None:
            return np.tile(self._m, (n, 1))
        return self.adaptive.margins(inputs, self._ceiling)[:, self._pick]

    def hold(self, ys: np.ndarray, inputs: np.ndarray | None = None) -> np.ndarray:
        """:meth:`holds` of each row of ``ys``, all at once (``inputs``: one row per row of ``ys``)."""
        ys = np.atleast_2d(np.asarray(ys, dtype=float))
        m = self.margins_of(len(ys), inputs)
        inside = np.all((ys >= self._lower + m) & (ys <= self._upper - m), axis=1)  # also False for NaN
        out = np.zeros(len(ys), dtype=bool)
        if inside.any():
            out[inside] = boxes_in_classifier(
                self.classifier, ys[inside], m[inside], self.threshold, bound=self.bound, pieces=self.pieces
            )
        return out

    def inner(self, fraction: float) -> ClassifierRegion:
        """The rescue region's own hand-back region (asked of real states)."""
        return self.region.inner(fraction)


def margin_region(
    region: Any, margins: dict[str, float], bound: str = "interval", pieces: int | None = None,
    adaptive: MarginScale | None = None,
) -> MarginRegion | ClassifierMarginRegion:  # fmt: skip
    """The rescue region ``region`` asked of a forecast with ``margins`` (a grid's or a classifier's).

    ``bound`` is how a classifier's score is bounded over a margin box (:data:`pidlab.lookup.BOUNDS`)
    and ``pieces`` caps a query's boxes at one halving (:func:`box_in_classifier`); a grid is asked
    cell by cell, exactly. ``adaptive``: margins that depend on the forecast's inputs (a
    classifier's only).

    Raises
    ------
    CoachingError
        ``region`` is no rescue region, a margin leaves nothing of it, ``bound`` is unknown, or
        ``pieces`` is below 1 or given for a lookup grid, or adaptive margins for a lookup grid.
    """
    check_bound(bound)
    check_pieces(pieces, region)
    check_adaptive(adaptive, region)
    if isinstance(region, ClassifierRegion):
        return ClassifierMarginRegion(region, margins, bound, pieces, adaptive)
    if isinstance(region, GridRegion):
        return MarginRegion(region, margins)
    raise CoachingError(f"the model predictor narrows a rescue region, not a {type(region).__name__}")


def check_bound(bound: str) -> None:
    """Refuse a score bound that is not one of :data:`pidlab.lookup.BOUNDS` (a :class:`CoachingError`)."""
    if bound not in BOUNDS:
        raise CoachingError(f"bound={bound!r}: expected one of {', '.join(BOUNDS)}", param="bound")


def check_pieces(pieces: int | None, region: Any = None) -> None:
    """Refuse a cap on a query's boxes that is not an integer >= 1 or None (a :class:`CoachingError`).

    With ``region``, also a cap on a lookup grid, which is asked cell by cell (no boxes to cap).
    """
    if not valid_pieces(pieces):
        raise CoachingError(
            f"pieces={pieces!r}: expected an integer in [1, {MAX_PIECES}] (or none: no cap)", param="pieces"
        )
    if pieces is not None and isinstance(region, GridRegion):
        raise CoachingError(
            f"pieces={pieces}: a cap on a query's boxes is for a classifier region; this rescue region is a "
            "lookup grid, asked cell by cell (leave pieces out)", param="pieces",
        )  # fmt: skip


def check_adaptive(adaptive: Any, region: Any = None) -> None:
    """Refuse adaptive margins for a lookup grid (narrowed once, cell by cell, by constant margins).

    Raises
    ------
    CoachingError
        ``adaptive`` is given (truthy) and ``region`` is a lookup grid.
    """
    if adaptive and isinstance(region, GridRegion):
        raise CoachingError(
            "adaptive margins need a classifier rescue region (a lookup grid is narrowed once, by "
            "constant margins); fit one with `pidlab rescue-classifier`, or measure constant margins",
            param="adaptive",
        )


def margin_variables(region: Any) -> tuple[str, ...]:
    """The variables a rescue region tests (a grid's and its guard's, or a classifier's)."""
    if isinstance(region, GridRegion):
        return (*region.grid.variables, *region.grid.guard)
    return tuple(region.variables)


def domain_box(region: Any) -> tuple[np.ndarray, np.ndarray]:
    """The box a rescue region lies in, over :func:`margin_variables`: ``(lower, upper)``.

    A classifier's domain box; a lookup grid's box and its guard's ranges. A forecast whose margin
    box passes :func:`margin_region` lies in it.
    """
    if isinstance(region, GridRegion):
        g = region.grid
        return (np.array([*g.lower, *(lo for lo, _ in g.guard.values())], dtype=float),
                np.array([*g.upper, *(hi for _, hi in g.guard.values())], dtype=float))  # fmt: skip
    clf = region.classifier
    return np.array(clf.lower, dtype=float), np.array(clf.upper, dtype=float)


def in_domain(region: Any, ys: np.ndarray) -> np.ndarray:
    """Whether each row of ``ys`` (the :func:`margin_variables`, in order) lies in :func:`domain_box`."""
    lo, hi = domain_box(region)
    ys = np.atleast_2d(np.asarray(ys, dtype=float))
    return np.all((ys >= lo) & (ys <= hi), axis=1)


def _check_room(name: str, margin: float, lo: float, hi: float) -> None:
    if 2.0 * margin >= hi - lo:
        raise CoachingError(
            f"the forecast's error on {name} ({margin:.4g}) is at least half the rescue region's range "
            f"[{lo:.4g}, {hi:.4g}]: nothing is left of the region; use predictor = 'exact'"
        )


def kept_share(
    region: Any, margins: dict[str, float], samples: int = 20000, seed: int = 0, bound: str = "interval",
    pieces: int | None = None, adaptive: MarginScale | None = None,
    inputs_of: Callable[[np.ndarray], np.ndarray] | None = None,
) -> float:  # fmt: skip
    """The share of the rescue region whose margin box fits in it (a Monte Carlo estimate).

    ``samples`` points drawn uniformly in the region (a grid: a marked cell, then a point in it, and
    the guard's ranges; a classifier: points of its domain box that it holds, drawn until
    ``samples`` are found or ``50 * samples`` drawn); 0 when no box fits at all. With ``adaptive``
    margins, each point's are those of a forecast made from it: ``inputs_of`` maps rows of the
    classifier's variables to the forecast's inputs (:func:`inputs_at_points`).
    """
    check_bound(bound)
    check_pieces(pieces, region)
    check_adaptive(adaptive, region)
    try:
        shrunk = margin_region(region, margins, bound, pieces, adaptive)
    except CoachingError:  # no box fits
        return 0.0
    rng = np.random.default_rng(seed)
    if isinstance(shrunk, ClassifierMarginRegion):
        points = classifier_points(shrunk.classifier, shrunk.threshold, samples, rng)
        if not len(points):
            return 0.0
        inputs = inputs_of(points) if adaptive is not None and inputs_of is not None else None
        return float(np.mean(shrunk.hold(points, inputs)))
    grid = region.grid
    marked = np.argwhere(np.asarray(grid.table, dtype=bool))
    if len(marked) == 0:
        return 0.0
    cells = marked[rng.integers(len(marked), size=samples)]
    points = np.array(grid.lower) + (cells + rng.random(cells.shape)) * grid.widths
    obs = np.zeros((samples, len(region.observation_names)))
    names = region.observation_names
    for k, v in enumerate(grid.variables):
        obs[:, names.index(v)] = points[:, k]
    for v, (lo, hi) in grid.guard.items():
        obs[:, names.index(v)] = rng.uniform(lo, hi, size=samples)
    return float(np.mean([shrunk.contains(o) for o in obs]))


def inputs_at_points(
    forecast: LinearForecast, model: mujoco.MjModel, base: np.ndarray, names: tuple[str, ...],
    variables: tuple[str, ...],
) -> Callable[[np.ndarray], np.ndarray]:  # fmt: skip
    """Rows of ``variables`` to the inputs of forecasts made there (:meth:`LinearForecast.observed_inputs`).

    ``base``: the observation the other variables keep (the operating point's); ``names``: the
    observation's variable names.
    """
    cols = [names.index(v) for v in variables]

    def inputs_of(points: np.ndarray) -> np.ndarray:
        obs = np.tile(np.asarray(base, dtype=float), (len(points), 1))
        obs[:, cols] = points
        return forecast.observed_inputs(model, obs)

    return inputs_of


def kept_inputs(region: Any, loaded: Any) -> Callable[[np.ndarray], np.ndarray] | None:
    """:func:`inputs_at_points` for a classifier ``region`` of ``loaded``'s env, about its operating point.

    None for any other region (a lookup grid has no adaptive margins).
    """
    if not isinstance(region, ClassifierRegion):
        return None
    from pidlab.linear.linearize import linearize
    from pidlab.plant.observation import observe_at
    from pidlab.plant.operating_point import resolve_operating_point

    card, op = loaded.require_card(), resolve_operating_point(loaded)
    forecast = linear_forecast(linearize(loaded), card, loaded.model)
    base = observe_at(card, loaded.model, op.qpos, op.qvel)
    return inputs_at_points(forecast, loaded.model, base, card.observation_names, region.classifier.variables)


def classifier_points(
    clf: RescueClassifier, threshold: float, samples: int, rng: np.random.Generator
) -> np.ndarray:
    """Up to ``samples`` points drawn uniformly in a classifier region (rejection from its domain box)."""
    lo, hi = np.array(clf.lower), np.array(clf.upper)
    found: list[np.ndarray] = []
    drawn = kept = 0
    while kept < samples and drawn < 50 * samples:
        batch = lo + (hi - lo) * rng.random((samples, len(lo)))
        drawn += samples
        inside = batch[clf.inside(batch, threshold)]
        found.append(inside)
        kept += len(inside)
    return np.concatenate(found)[:samples] if found else np.zeros((0, len(lo)))
