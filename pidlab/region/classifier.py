"""Rescue regions as a learned classifier: every variable that decides a rescue, where a grid gets too big.

A lookup grid (:mod:`pidlab.region.rescue`) covers two to four variables and leaves the rest to a
guard box; on InvertedDoublePendulum that box (upper pole 0.03 rad, cart 0.2 m) throws away most
of the states the coach rescues. A **classifier region** covers all of them:

1. **Domain.** A box about the operating point over the chosen observation variables (a joint's
   position, its sine, or its velocity); a state the env's termination rule ends is dropped, so the
   domain is the env's own termination domain cut by the box (the box bounds the velocities, which
   no termination rule does).
2. **Labels.** ``samples + calibration`` states drawn uniformly in the domain are simulated in
   MuJoCo with the coach's real discrete law, exactly as a grid cell's probes are: a state is
   *rescued* when the coach brings it into the spec's certified core (or, for a coach certified by
   simulation only, survives the horizon) without a termination on the way. No agent step is
   taken first: the region serves the ``predictive`` trigger.
3. **Fit.** A small network (``tanh`` hidden layers, one linear output) is fitted to the labels of
   the first ``samples`` states by weighted cross-entropy (failures weigh ``negative_weight``
   times more), deterministically from ``seed`` (:func:`fit_layers`).
   **Focus** (``focus > 0``): most of a large domain is plainly lost (Hopper: 92 % of the states
   over its legs), and uniform labels spend most simulations there. So ``focus`` further states
   are drawn uniformly among those the first fit scores at least :func:`focus_level` (all but
   the lowest-scoring :data:`FOCUS_QUANTILE` of the rescued fitted states score as high), labelled
   the same way, and the network is fitted again on both. The threshold and every check below
   still use uniform draws only, so focusing changes which network is checked, not the checks.
4. **Threshold.** The calibration states set it: the highest score a failure among them has.
5. **Validation**, as for the grid: ``validation`` fresh states drawn uniformly inside the
   region are simulated; a failure raises the threshold past its score and a new fresh draw
   follows, until a draw has none (rule of three: a failure rate below ``3 / validation`` with
   95 % confidence).
   **A tolerated false-claim rate** (``false_claims`` = alpha > 0): a draw is accepted when its
   failures show a failure rate below alpha with 95 % confidence (the one-sided Clopper-Pearson
   bound, :func:`failure_bound`; :func:`allowed_failures`). The failures of the accepted draw stay
   inside: the region claims states its coach does not rescue, at a measured rate, where the
   outcome is too irregular for any threshold to rank every failure below every rescue
   (Walker2d). alpha = 0 is the rule above.
   **At the edge**: the trigger meets the region at its edge, where an agent's actions take the
   state, and a thin sliver of false claims there (a pole near its limit, moving out) escapes a
   uniform draw. So ``validation`` more fresh states are drawn inside the region *among its
   lowest-scoring* ``edge_share`` (scores from the threshold to the ``edge_share`` quantile of the
   uniform draw's), and validated the same way: a failure raises the threshold, a new edge draw
   follows, until one has none (``edge_share = 0``: no edge draw).
6. **Coverage**: ``coverage`` fresh states over the domain tell which are rescuable; the coverage
   is the share of those the region holds. The spec's grid region, if it has one, is scored on the
   same states, so the two are compared over the same termination domain.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import beta

from pidlab import __version__
from pidlab.checks import integer, number
from pidlab.checks import seed as check_seed
from pidlab.controller.spec import CoachSpec, law_digest
from pidlab.errors import RegionError
from pidlab.lookup import MAX_CLASSIFIER_VARIABLES, MAX_WIDTH, RescueClassifier, is_classifier
from pidlab.plant.model import LoadedModel
from pidlab.region.coverage import draw_near, draw_states
from pidlab.region.networks import fit_tanh_network
from pidlab.region.rescue import (
    MAX_ROUNDS,
    STARTS_ON_FLOOR,
    _Domain,
    _Estimate,
    check_into,
    simulations,
    state_domain,
)  # fmt: skip
from pidlab.region.takeover import ClassifierRegion, GridRegion, region_from_bounds

Progress = Callable[[str, "float | None"], None]

MAX_SAMPLES = 2_000_000
"""The most labelled states an estimate may simulate per stage."""

FOCUS_QUANTILE = 0.01
"""The share of the rescued fitted states the focus zone may leave out (their lowest first-fit scores)."""


@dataclass(frozen=True)
class ClassifierSettings:
    """What a classifier rescue region covers and how hard it looks.

    Attributes
    ----------
    variables : tuple of str
        Observation variables (a hinge or slide joint's position, its sine, or its velocity): every
        one that decides a rescue.
    half_range : tuple of float
        The domain box's half-widths about the operating point's observation.
    samples : int
        Labelled states the network is fitted on.
    calibration : int
        Further labelled states that set the threshold.
    validation : int
        Fresh states per validation draw.
    coverage : int
        Fresh states over the domain for the coverage.
    width : int
        Units per hidden layer (two hidden layers).
    epochs : int
        Passes over the fitted states.
    negative_weight : float
        Weight of a failure's loss against a rescue's.
    horizon_s : float
        Simulated time per rescue.
    seed : int
    edge_share : float
        The share of the region, its lowest scores, that the edge validation draws from (0: none).
    focus : int
        Further labelled states drawn where a first fit scores at least :func:`focus_level`, fitted
        on too (0: none).
    near : int
        Further labelled states drawn near where the coach hands back and near the operating point
        (:func:`pidlab.region.coverage.draw_near`), fitted on too (0: none): a domain of many
        variables has no uniform label near either.
    into : {"core", "box"}
        Where a rescue ends (:data:`pidlab.region.rescue.RESCUE_ENDS`): the certified core (a coach
        certified by simulation: the horizon held), or the horizon held and ended in the
        recoverable box ``[bounds.box]``.
    false_claims : float
        The failure rate inside the region tolerated (alpha in [0, 0.5)): a validation draw is
        accepted when its failures show a rate below alpha with 95 % confidence. 0: none (a draw
        is accepted only without a failure); otherwise at least :func:`failure_bound` of no failure
        in ``validation`` states, the least that many states can show.
    """

    variables: tuple[str, ...]
    half_range: tuple[float, ...]
    samples: int = 160_000
    calibration: int = 25_000
    validation: int = 2000
    coverage: int = 20_000
    width: int = 64
    epochs: int = 100
    negative_weight: float = 3.0
    horizon_s: float = 3.0
    seed: int = 0
    edge_share: float = 0.05
    focus: int = 0
    into: str = "core"
    near: int = 0
    false_claims: float = 0.0

    def __post_init__(self) -> None:
        """Refuse settings out of range at once (:class:`RegionError` naming the field)."""
        _check_settings(self)


def _check_settings(s: ClassifierSettings) -> None:
    k = len(s.variables)
    if not 1 <= k <= MAX_CLASSIFIER_VARIABLES or len(s.half_range) != k or len(set(s.variables)) != k:
        raise RegionError(
            f"classifier domain: expected 1 to {MAX_CLASSIFIER_VARIABLES} distinct variables with a "
            "half-range each"
        )
    for name, h in zip(s.variables, s.half_range, strict=True):
        number(h, f"half-range of {name}", RegionError, low=0.0, low_open=True)
    counts = (("samples", 100), ("calibration", 100), ("validation", 1), ("coverage", 1), ("focus", 0),
              ("near", 0))  # fmt: skip
    for name, low in counts:
        integer(getattr(s, name), name, RegionError, low=low, high=MAX_SAMPLES, param=name)
    integer(s.width, "width", RegionError, low=2, high=MAX_WIDTH, param="width")
    integer(s.epochs, "epochs", RegionError, low=1, high=10_000, param="epochs")
    number(s.negative_weight, "negative_weight", RegionError, low=0.0, low_open=True, high=1e6)
    number(s.horizon_s, "horizon_s", RegionError, low=0.0, low_open=True, high=600.0)
    number(s.edge_share, "edge_share", RegionError, low=0.0, high=1.0, param="edge_share")
    check_seed(s.seed, "seed", RegionError, param="seed")
    check_into(s.into)
    number(
        s.false_claims, "false_claims", RegionError, low=0.0, high=0.5, high_open=True, param="false_claims"
    )
    least = failure_bound(0, s.validation)
    if 0.0 < s.false_claims < least:
        floor = f"0 or at least {least:.3g}" if least < 0.5 else "0"
        raise RegionError(
            f"false_claims={s.false_claims:g}: {s.validation} validation state(s) with no failure show a "
            f"failure rate below {least:.3g} at best; expected {floor} (or more validation states)",
            param="false_claims",
        )


def failure_bound(failures: int, n: int) -> float:
    """Upper 95 % bound on the failure rate when ``failures`` of ``n`` draws failed.

    No failure: the rule of three, ``3 / n`` (at most 1). Otherwise the one-sided Clopper-Pearson bound, the
    rate ``p`` at which ``failures`` or fewer would come up with probability 0.05.
    """
    if failures <= 0:
        return min(3.0 / n, 1.0)
    if failures >= n:
        return 1.0
    return float(beta.ppf(0.95, failures + 1, n - failures))


def allowed_failures(n: int, false_claims: float) -> int:
    """The most failures a draw of ``n`` may hold whose :func:`failure_bound` stays within ``false_claims``.

    0 when ``false_claims`` is 0 (a draw is accepted only without a failure).
    """
    if false_claims <= 0.0:
        return 0
    k = 0
    while k < n and failure_bound(k + 1, n) <= false_claims:
        k += 1
    return k


@dataclass(frozen=True)
class ClassifierRescue:
    """A validated classifier rescue region and how it was found.

    Attributes
    ----------
    classifier : RescueClassifier
    settings : ClassifierSettings
    coverage : float
        Share of the rescuable domain states the region holds.
    coverage_grid : float or None
        The spec's grid region on the same states (None without one).
    rescued_fraction : float
        Share of the domain states the coach rescues.
    volume : float
        Share of the domain states the region holds.
    validation_rounds : int
        Draws until one had no failure.
    failures_removed : int
        Failures found (and excluded by a higher threshold) in the earlier draws.
    edge_rounds : int
        Edge draws until one had no failure (0: no edge validation).
    edge_failures_removed : int
        Failures the edge draws found (and excluded by a higher threshold).
    calibration_accuracy : float
        Share of calibration states the network's sign classifies right (score >= 0: rescued).
    validation_failures : int
        Failures in the accepted validation draw (0 unless ``settings.false_claims`` tolerates some:
        they stay inside the region).
    edge_failures : int
        The same for the accepted edge draw.
    provenance : dict
    reused : int
        Of the simulations, the outcomes read from the labels' journal of an earlier, stopped run
        instead of simulated again (not compared, not in the provenance: a resumed estimate writes
        the same region).
    """

    classifier: RescueClassifier
    settings: ClassifierSettings
    coverage: float
    coverage_grid: float | None
    rescued_fraction: float
    volume: float
    validation_rounds: int
    failures_removed: int
    edge_rounds: int
    edge_failures_removed: int
    calibration_accuracy: float
    validation_failures: int = 0
    edge_failures: int = 0
    provenance: dict[str, Any] = field(default_factory=dict, compare=False, hash=False)
    reused: int = field(default=0, compare=False)

    @property
    def failure_bound_95(self) -> float:
        """Upper 95 % bound on the failure rate inside: :func:`failure_bound` of the accepted draw."""
        return failure_bound(self.validation_failures, self.settings.validation)

    def to_table(self) -> dict[str, Any]:
        """The spec's ``[bounds.rescue]`` table."""
        return {**self.classifier.to_table(), "provenance": dict(self.provenance)}


THIN = "too thin a share of its domain to draw from uniformly"
KEPT = {
    "validation": f"the region: {THIN} (fit over a smaller --domain)",
    "edge validation": f"the region's edge band: {THIN} (--edge-share 0 skips the edge draw)",
    "focus": f"the first fit's focus, states it scores like the rescued ones: {THIN} (--focus 0 skips it)",
}
"""What each draw kept by the classifier holds, for the error when its domain holds (almost) none of it."""


def fit_layers(
    x: np.ndarray, y: np.ndarray, width: int, epochs: int, negative_weight: float, seed: int
) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """Fit a two-hidden-layer ``tanh`` network's score to labels, deterministically.

    Parameters
    ----------
    x : ndarray, shape (n, k)
        Inputs, scaled to [-1, 1].
    y : ndarray of bool, shape (n,)
        Labels (True: rescued).
    width, epochs : int
    negative_weight : float
        Loss weight of a False label against a True one.
    seed : int

    Returns
    -------
    tuple of (weights, bias)
        Per layer, weights of shape ``(inputs, outputs)``; the score is the last layer's output.
    """
    import torch

    xt, yt = torch.tensor(x, dtype=torch.float32), torch.tensor(y, dtype=torch.float32)
    return fit_tanh_network(x.shape[1], 1, width, seed,
                            lambda net: _train(net, xt, yt, epochs, negative_weight))  # fmt: skip


def _train(net: Any, x: Any, y: Any, epochs: int, negative_weight: float) -> None:
    """Adam with a cosine-decayed step size over ``epochs`` passes of shuffled batches.

    A batch is 1/50 of the states (32 to 1,024), so that a pass takes at least 50 steps whatever
    the number of states.
    """
    import torch

    batch = min(max(len(x) // 50, 32), 1024)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(opt, epochs)
    weight = torch.where(y > 0.5, 1.0, float(negative_weight))
    for _ in range(epochs):
        order = torch.randperm(len(x))
        for i in range(0, len(x), batch):
            b = order[i : i + batch]
            loss = torch.nn.functional.binary_cross_entropy_with_logits(net(x[b]).squeeze(1), y[b],
                                                                        weight=weight[b])  # fmt: skip
            opt.zero_grad()
            loss.backward()
            opt.step()
        schedule.step()


def calibrated_threshold(scores: np.ndarray, rescued: np.ndarray) -> float:
    """The highest score of a failure (every failure outside); below every score when none failed."""
    failed = scores[~rescued]
    return float(failed.max()) if failed.size else float(scores.min()) - 1.0


def raised_threshold(threshold: float, failed_scores: np.ndarray) -> float:
    """The threshold moved just past the highest score of the failures found inside the region."""
    if not failed_scores.size:
        return threshold
    return float(np.nextafter(max(threshold, float(failed_scores.max())), np.inf))


@dataclass
class _Work:
    """The estimate's working state: the simulations, the domain, the clock and the progress."""

    est: _Estimate
    settings: ClassifierSettings
    started: float
    report: Progress


@contextlib.contextmanager
def _working(
    spec: CoachSpec,
    loaded: LoadedModel,
    s: ClassifierSettings,
    workers: int | None,
    progress: Progress | None,
    journal: str | Path | None = None,
) -> Iterator[_Work]:
    def domain_of(card: Any, model: LoadedModel, y_op: np.ndarray) -> _Domain:
        return state_domain(s.variables, s.half_range, card, model, y_op)

    with simulations(spec, loaded, s, domain_of, workers, progress, journal, s.into) as (est, _, _):
        yield _Work(est, s, time.perf_counter(), progress or (lambda stage, f: None))


def estimate_classifier(
    spec: CoachSpec,
    loaded: LoadedModel,
    settings: ClassifierSettings,
    workers: int | None = None,
    progress: Progress | None = None,
    journal: str | Path | None = None,
) -> ClassifierRescue:
    """Estimate, validate and score a classifier rescue region (see the module docstring).

    Parameters
    ----------
    spec : CoachSpec
        The coach, with its certified core (``pidlab bounds SPEC --write`` first).
    loaded : LoadedModel
    settings : ClassifierSettings
    workers : int, optional
        Worker processes for the simulations (default: the machine's cores).
    progress : callable, optional
        ``progress(stage, fraction)``.
    journal : path, optional
        A folder that keeps every simulation's outcome as it is found: the same estimate run again
        (after a stop) reads them instead of simulating them, and gives the same region
        (:mod:`pidlab.region.journal`). None keeps nothing.

    Returns
    -------
    ClassifierRescue

    Raises
    ------
    RegionError
        A variable that is not a joint's position, sine or velocity; no certified core; a domain the
        termination rule leaves (almost) empty; a region that leaves out the operating point, or that
        validation cannot clear in :data:`MAX_ROUNDS` draws.
    """
    with _working(spec, loaded, settings, workers, progress, journal) as work:
        s, est = settings, work.est
        labelled = draw_states(work.est, s.samples + s.calibration)
        rescued, _ = est.rescued(labelled, "labelling")
        box = _box(work.est.domain)
        anchor = _anchor(spec, loaded, s.variables, box)
        unfitted = RescueClassifier(s.variables, *box, layers=(), coach=law_digest(spec), anchor=anchor)
        layers, focused = _fitted(work, unfitted, labelled[: s.samples], rescued[: s.samples])
        scores = replace(unfitted, layers=layers).scores(labelled[s.samples :])
        accuracy = float(np.mean((scores >= 0.0) == rescued[s.samples :]))
        clf = replace(unfitted, layers=layers, threshold=calibrated_threshold(scores, rescued[s.samples :]))
        clf, inside, scores_inside = _validate(work, clf, s.validation)
        clf, edge = _validate_edge(work, clf, scores_inside)
        return _scored(spec, work, clf, (inside, edge, accuracy), focused)


def _anchor(
    spec: CoachSpec, loaded: LoadedModel, variables: tuple[str, ...], box: tuple[tuple[float, ...], ...]
) -> tuple[float, ...] | None:
    """Where a coach designed about a point of its own hands back (a balance coach's posture), or None.

    Raises
    ------
    RegionError
        That point lies outside the domain box.
    """
    from pidlab.controller.balance import design_observation

    y = design_observation(spec, loaded, variables)
    if y is None:
        return None
    lower, upper = box
    rows = zip(variables, y, lower, upper, strict=True)
    outside = [f"{v} {x:.4g}" for v, x, lo, hi in rows if not lo <= x <= hi]
    if outside:
        raise RegionError(
            f"the posture the coach regulates to lies outside the domain ({', '.join(outside)}); "
            "widen --domain"
        )
    return tuple(float(v) for v in y)


def focus_level(rescued_scores: np.ndarray) -> float:
    """The first fit's score reached by all the rescued fitted states but the lowest :data:`FOCUS_QUANTILE`.

    Raises
    ------
    RegionError
        No fitted state was rescued: there is nothing to focus on.
    """
    if not rescued_scores.size:
        raise RegionError(
            "focus: no fitted state was rescued, so there is no zone to focus on; widen the domain or "
            "label more states (--samples)"
        )
    return float(np.quantile(rescued_scores, FOCUS_QUANTILE))


def _fitted(
    work: _Work, unfitted: RescueClassifier, labelled: np.ndarray, rescued: np.ndarray
) -> tuple[tuple[tuple[np.ndarray, np.ndarray], ...], dict[str, Any]]:
    """The network fitted on the uniform labels and (``focus``, ``near``) the further ones; their facts."""
    s = work.settings
    xs, ys = [unfitted.scaled(labelled)], [rescued]
    facts: dict[str, Any] = {}
    if s.focus:
        work.report("fitting", None)
        layers = fit_layers(xs[0], ys[0], s.width, s.epochs, s.negative_weight, s.seed)
        first = replace(unfitted, layers=layers)
        level = focus_level(first.scores(labelled[rescued]))
        drawn = draw_states(work.est, s.focus, keep=lambda v: first.scores(v) >= level,
                            kept=KEPT["focus"])  # fmt: skip
        ok, _ = work.est.rescued(drawn, "focus")
        xs, ys = [*xs, unfitted.scaled(drawn)], [*ys, ok]
        facts |= {"focus": s.focus, "focus_level": level, "focus_rescued": float(ok.mean())}
    if s.near:
        centre = (np.array(unfitted.lower) + np.array(unfitted.upper)) / 2.0
        centres = np.unique(np.vstack([unfitted.anchor_point(), centre]), axis=0)
        drawn = draw_near(work.est, s.near, centres)
        ok, _ = work.est.rescued(drawn, "near")
        xs, ys = [*xs, unfitted.scaled(drawn)], [*ys, ok]
        facts |= {"near": s.near, "near_rescued": float(ok.mean())}
    work.report("fitting", None)
    return fit_layers(np.vstack(xs), np.concatenate(ys), s.width, s.epochs, s.negative_weight, s.seed), facts


def _box(d: _Domain) -> tuple[tuple[float, ...], tuple[float, ...]]:
    return tuple(float(v) for v in d.lower), tuple(float(v) for v in d.upper)


def _validate(
    work: _Work, clf: RescueClassifier, n: int
) -> tuple[RescueClassifier, tuple[int, int, int], np.ndarray]:
    """Fresh draws inside until one is accepted: the classifier, (rounds, removed, kept), its scores."""
    anchor = clf.anchor_point()[None, :]
    where = "the operating point" if clf.anchor is None else "the point its coach regulates to"

    def inside(c: RescueClassifier) -> Callable[[np.ndarray], np.ndarray]:
        if not c.inside(anchor)[0]:
            raise RegionError(
                f"the classifier region leaves out {where} (where the coach hands back): a "
                "failure scores as high as it; fit on more samples (--samples) or longer (--epochs)"
            )
        return c.inside

    return _until_clean(work, clf, n, inside, "validation")


def _until_clean(
    work: _Work, clf: RescueClassifier, n: int, keep_of: Callable[[RescueClassifier], Callable], label: str
) -> tuple[RescueClassifier, tuple[int, int, int], np.ndarray]:
    """Draws of ``n`` states that ``keep_of(clf)`` keeps, until one is accepted.

    A draw is accepted with no more failures than :func:`allowed_failures` tolerates (none by
    default); otherwise each of its failures raises the threshold past its score. Returns the
    classifier, (rounds, failures removed by the earlier draws, failures kept in the accepted
    one) and the accepted draw's scores.
    """
    removed, allowed = 0, allowed_failures(n, work.settings.false_claims)
    for k in range(1, MAX_ROUNDS + 1):
        drawn = draw_states(work.est, n, keep=keep_of(clf), kept=KEPT[label])
        ok, _ = work.est.rescued(drawn, f"{label} {k}")
        failed = int((~ok).sum())
        if failed <= allowed:
            return clf, (k, removed, failed), clf.scores(drawn)
        removed += failed
        clf = replace(clf, threshold=raised_threshold(clf.threshold, clf.scores(drawn[~ok])))
    raise RegionError(f"the classifier region still failed {label} after {MAX_ROUNDS} draws")


def edge_width(threshold: float, scores_inside: np.ndarray, share: float) -> float:
    """The width of the region's edge in score: from the threshold to the ``share`` quantile of the scores."""
    if share <= 0.0 or not scores_inside.size:
        return 0.0
    return max(float(np.quantile(scores_inside, share)) - threshold, 0.0)


def _validate_edge(
    work: _Work, clf: RescueClassifier, scores_inside: np.ndarray
) -> tuple[RescueClassifier, tuple[int, int, int, float]]:
    """Draws at the region's edge until one is accepted: the classifier, (rounds, removed, kept, band)."""
    s = work.settings
    width = edge_width(clf.threshold, scores_inside, s.edge_share)
    if width <= 0.0:
        return clf, (0, 0, 0, 0.0)

    def at_edge(c: RescueClassifier) -> Callable[[np.ndarray], np.ndarray]:
        return lambda v: c.inside(v) & (c.scores(v) <= c.threshold + width)

    clf, (rounds, removed, kept), _ = _until_clean(work, clf, s.validation, at_edge, "edge validation")
    return clf, (rounds, removed, kept, width)


def _scored(
    spec: CoachSpec,
    work: _Work,
    clf: RescueClassifier,
    how: tuple[tuple[int, int, int], tuple[int, int, int, float], float],
    focused: dict[str, Any],
) -> ClassifierRescue:
    """Coverage over fresh domain states, the spec's grid region on the same ones, and the provenance."""
    s, est = work.settings, work.est
    states = draw_states(work.est, s.coverage)
    rescued, obs = est.rescued(states, "coverage")
    inside = clf.inside(states)
    grid = _grid_region(spec, est.pool.sim.card.observation_names)
    in_grid = None if grid is None else np.array([grid.contains(o) for o in obs], dtype=bool)
    held = int(rescued.sum())

    def share(mask: np.ndarray) -> float:
        return float((mask & rescued).sum()) / held if held else 0.0

    (rounds, removed, kept), (edge_rounds, edge_removed, edge_kept, band), accuracy = how
    result = ClassifierRescue(
        clf, s, share(inside), None if in_grid is None else share(in_grid), float(rescued.mean()),
        float(inside.mean()), rounds, removed, edge_rounds, edge_removed, accuracy, kept, edge_kept,
    )  # fmt: skip
    elapsed = round(time.perf_counter() - work.started, 1)
    facts: dict[str, Any] = {"simulations": est.simulations, "elapsed_s": elapsed, "coverage_rescuable": held,
                             **focused}  # fmt: skip
    if edge_rounds:
        facts |= {"edge_share": s.edge_share, "edge_band": band, "edge_samples": s.validation,
                  "edge_rounds": edge_rounds, "edge_failures_removed": edge_removed}  # fmt: skip
        if s.false_claims:
            facts["edge_failures"] = edge_kept
    if s.false_claims:
        facts["false_claims_tolerated"] = s.false_claims
    if est.grounded:
        facts["starts"] = STARTS_ON_FLOOR
    return replace(result, provenance=_provenance(result, facts), reused=est.reused)


def _grid_region(spec: CoachSpec, names: tuple[str, ...]) -> GridRegion | None:
    """The spec's lookup-grid rescue region, if it has one (scored on the same states)."""
    rescue = (spec.bounds or {}).get("rescue")
    if rescue is None or is_classifier(rescue):
        return None
    region = region_from_bounds(spec.bounds, names, "rescue", spec.name)
    return region if isinstance(region, GridRegion) else None


def _provenance(r: ClassifierRescue, facts: dict[str, Any]) -> dict[str, Any]:
    """How the region was found, for ``[bounds.rescue.provenance]``."""
    import datetime

    s = r.settings
    out: dict[str, Any] = {
        "method": "simulation: classifier fitted on labelled states, validated on fresh states inside",
        "domain": dict(zip(s.variables, s.half_range, strict=True)),
        "domain_rule": "box about the operating point, states the env's termination rule ends (or outside a "
        "joint's range) dropped",
        "horizon_s": s.horizon_s,
        "rescued_into": s.into,
        "samples": s.samples,
        "calibration": s.calibration,
        "width": s.width,
        "epochs": s.epochs,
        "negative_weight": s.negative_weight,
        "calibration_accuracy": round(r.calibration_accuracy, 6),
        "validation_samples": s.validation,
        "validation_failures": r.validation_failures,
        "validation_rounds": r.validation_rounds,
        "failures_removed": r.failures_removed,
        "failure_probability_95": r.failure_bound_95,
        "coverage_samples": s.coverage,
        **facts,
        "coverage_rescue": r.coverage,
        "rescued_fraction": r.rescued_fraction,
        "volume_rescue": r.volume,
        "seed": s.seed,
        "date": datetime.date.today().isoformat(),
        "pidlab_version": __version__,
    }
    if r.coverage_grid is not None:
        out["coverage_grid"] = r.coverage_grid
    return out


def with_classifier(spec: CoachSpec, region: ClassifierRescue, takeover: bool = True) -> CoachSpec:
    """``spec`` with ``region`` as its ``[bounds.rescue]`` (and its takeover region when ``takeover``).

    A ``[bounds.forecast]`` measured on the former region is dropped: the model predictor narrows
    lookup grids only.
    """
    bounds = dict(spec.bounds or {})
    bounds["rescue"] = region.to_table()
    bounds.pop("forecast", None)
    if takeover:
        bounds["takeover"] = "rescue"
    return replace(spec, bounds=bounds)


def classifier_region(spec: CoachSpec, observation_names: tuple[str, ...]) -> ClassifierRegion:
    """The spec's classifier rescue region, as the coaching wrapper asks it.

    Raises
    ------
    RegionError
        The spec's rescue region is no classifier.
    """
    region = region_from_bounds(spec.bounds, observation_names, "rescue", spec.name)
    if not isinstance(region, ClassifierRegion):
        raise RegionError(f"{spec.name}: its rescue region is a lookup grid, not a classifier")
    return region
