"""The arguments of :func:`pidlab.rl.train.train` and :func:`pidlab.rl.train.resume`, checked first.

Each public function of pidlab refuses a bad argument with a :class:`~pidlab.errors.PidlabError`
whose ``param`` names it (a path given as ``None`` or ``""``, a recipe given as its file's path, a
budget below what a run already did), before anything is read or written, instead of failing deep
inside with an ``AttributeError`` or ``TypeError``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pidlab.checks import boolean, path_argument, shown, strings
from pidlab.controller.spec import CoachSpec
from pidlab.errors import RecipeError, RunDirError, SpecError
from pidlab.rl.recipe import MAX_STEPS, Recipe


def _argv(argv: Any, error: type[RunDirError]) -> None:
    if argv is not None:
        strings(argv, "argv", error, what="command-line words")


def check_train_arguments(
    recipe: Any, spec: Any, run_dir: Any, coach_source: Any, progress_bar: Any, argv: Any
) -> Path:
    """Check what :func:`~pidlab.rl.train.train` was given; the run folder as a ``Path``.

    Raises
    ------
    RecipeError
        ``recipe`` is not a :class:`~pidlab.rl.recipe.Recipe` (a path: load it with ``load_recipe``).
    SpecError
        ``spec`` is neither ``None`` nor a :class:`~pidlab.controller.spec.CoachSpec`, or is for
        another env than the recipe.
    RunDirError
        ``run_dir`` is no path (``None``, ``""``), ``coach_source`` not a string, ``progress_bar``
        not a bool, or ``argv`` not a list of strings.
    """
    if not isinstance(recipe, Recipe):
        hint = "; read a recipe file with pidlab.load_recipe(path)" if isinstance(recipe, (str, Path)) else ""
        raise RecipeError(f"recipe={shown(recipe)}: expected a Recipe{hint}", param="recipe")
    if spec is not None and not isinstance(spec, CoachSpec):
        hint = "; read a spec file with pidlab.load_spec(path)" if isinstance(spec, (str, Path)) else ""
        raise SpecError(f"spec={shown(spec)}: expected a CoachSpec or None (no coach){hint}", param="spec")
    if spec is not None and spec.env_id != recipe.env_id:
        raise SpecError(
            f"spec={spec.name!r}: a coach for {spec.env_id}, but the recipe is for {recipe.env_id}",
            param="spec",
        )
    from pidlab.rl.couplings import check_couplings

    check_couplings(recipe, spec)
    folder = path_argument(run_dir, "run_dir", RunDirError, what="the run's folder")
    if coach_source is not None and not isinstance(coach_source, str):
        raise RunDirError(f"coach_source={shown(coach_source)}: expected a str or None", param="coach_source")
    boolean(progress_bar, "progress_bar", RunDirError)
    _argv(argv, RunDirError)
    return folder


def _steps_done(run_dir: Path) -> int | None:
    """The env steps the run's ``summary.json`` says it did (None: no summary, or one that does not say)."""
    from pidlab.files import load_json

    path = run_dir / "summary.json"
    if not path.is_file():
        return None
    try:
        done = load_json(path, "run summary", RunDirError).get("env_steps")
    except (RunDirError, AttributeError):
        return None  # a damaged summary: resume warns about it and writes it again
    return done if isinstance(done, int) and not isinstance(done, bool) else None


def check_resume_arguments(run_dir: Any, steps: Any, progress_bar: Any, argv: Any) -> Path:
    """Check what :func:`~pidlab.rl.train.resume` was given; the run folder as a ``Path``.

    A new budget ``steps`` must not be below the env steps the run already did: a finished run of
    60,000 steps asked for 100 is refused, not returned as if done (nothing is changed).

    Raises
    ------
    RunDirError
        ``run_dir`` is no path, ``steps`` is not an integer in ``[1, 1e12]`` or is below what the
        run's ``summary.json`` says it did, ``progress_bar`` is not a bool, or ``argv`` is not a
        list of strings.
    """
    folder = path_argument(run_dir, "run_dir", RunDirError, what="a run's folder")
    if steps is not None:
        if isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= MAX_STEPS:
            raise RunDirError(
                f"steps={shown(steps)}: expected a positive number of env steps in [1, 1e12]",
                param="steps",
            )
        done = _steps_done(folder)
        if done is not None and steps < done:
            raise RunDirError(
                f"steps={steps}: the run has already done {done} env steps ({folder}); expected a "
                f"budget of at least {done}, or no steps to keep the run's own",
                param="steps",
            )
    boolean(progress_bar, "progress_bar", RunDirError)
    _argv(argv, RunDirError)
    return folder
