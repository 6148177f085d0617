"""The ``pidlab`` command line.

Every verb is a thin layer over the Python API: parse options, call, print. Bad input
(a :class:`pidlab.errors.PidlabError`, or a usage error such as ``--steps lots``) becomes one line
on stderr and exit code 2; an interrupt (Ctrl-C, SIGINT or SIGTERM) exits with code 130.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import functools
import json
import os
import re
import sys
from collections.abc import Callable, Iterator, Sequence
from typing import Annotated, Any, NoReturn, TypeVar

import numpy as np
import typer
from typer.core import TyperGroup

try:  # Typer 0.2x vendors Click; older Typer uses the click package
    from typer._click import exceptions as _click
    from typer._click.globals import get_current_context
except ImportError:  # pragma: no cover
    from click import exceptions as _click  # type: ignore[no-redef]
    from click import get_current_context  # type: ignore[no-redef]

from pidlab import __version__
from pidlab.errors import PidlabError
from pidlab.interrupts import ignore_stops, sigterm_interrupts

EXIT_BAD_INPUT = 2
"""Exit code of bad input: a usage error or a :class:`PidlabError` (one line on stderr)."""
EXIT_INTERRUPTED = 130
"""Exit code of every command stopped by SIGINT (Ctrl-C) or SIGTERM (128 + SIGINT, as shells report)."""
MAX_LINEARIZE_STATES = 1000
"""The largest model ``pidlab linearize`` analyzes (states: 2 nv + na); its PBH tests take
four SVDs of about n x n per mode, hours beyond this size."""
LONG_WORK_S = 10.0
"""Work expected to take longer than this says so first (when no progress bar is shown)."""

_EXPECTED = (
    (re.compile(r"valid integer"), "expected an integer"),
    (re.compile(r"valid (?:number|float)"), "expected a number"),
    (re.compile(r"valid boolean"), "expected true or false"),
    (re.compile(r"is not in the range (?P<range>.+?)\.?$"), "expected a value in {range}"),
    (re.compile(r"is not (?:one of )?(?P<choices>'.+?)\.?$"), "expected one of {choices}"),
)
"""Click's and Typer's messages about a value of the wrong kind, and how pidlab says them."""
_QUOTED_VALUE = re.compile(r"^(?P<value>'.*?'|\S+) is not ")


def _given(exc: Exception) -> str | None:
    """The value a :class:`BadParameter` refused, quoted, when the error says it."""
    errors = getattr(exc.__cause__, "errors", None)  # Typer checks values with pydantic
    if callable(errors):
        found = errors()
        if found and "input" in found[0]:
            return repr(str(found[0]["input"]))
    hit = _QUOTED_VALUE.match(str(getattr(exc, "message", "")))
    return hit["value"] if hit else None


def usage_message(exc: Exception) -> str:
    """A Click usage error in one line, e.g. ``--steps 'lots': expected an integer``, and where help is.

    Parameters
    ----------
    exc : click.ClickException
        Click's (or Typer's vendored Click's) exception.
    """
    ctx = getattr(exc, "ctx", None)
    where = f" (see '{ctx.command_path} --help')" if ctx is not None else ""
    param = getattr(exc, "param", None)
    if isinstance(exc, _click.BadParameter) and not isinstance(exc, _click.MissingParameter) and param:
        opts = [o for o in getattr(param, "opts", []) if o.startswith("-")]
        hint = max(opts, key=len) if opts else param.human_readable_name
        given = _given(exc)
        head = f"{hint} {given}" if given else hint
        for pattern, expected in _EXPECTED:
            hit = pattern.search(exc.message)
            if hit:
                return f"{head}: {expected.format(**hit.groupdict())}{where}"
        return f"{head}: {exc.message.rstrip('.')}{where}"
    text = " ".join(str(getattr(exc, "format_message", exc.__str__)()).split())  # one line
    return f"{text[:1].lower()}{text[1:].rstrip('.')}{where}"


def _plain_help(command: Any) -> None:
    """Show every help text of ``command``'s tree as written.

    The help is drawn with rich, which reads ``[...]`` as markup and drops it: "Kept in
    [bounds.forecast]" would read "Kept in ." Each text is escaped once, in the tree the command line
    runs (built afresh for each run; the CLI reference page reads the texts unescaped).
    """
    from rich.markup import escape

    if getattr(command, "_pidlab_plain", False):
        return
    command._pidlab_plain = True
    for owner in (command, *command.params):
        for field in ("help", "short_help"):
            text = getattr(owner, field, None)
            if isinstance(text, str):
                setattr(owner, field, escape(text))
    for sub in getattr(command, "commands", {}).values():
        _plain_help(sub)


class PidlabGroup(TyperGroup):
    """The ``pidlab`` group: every usage error in one line, every interrupt exits 130.

    Click prints a usage error as a box with the usage; pidlab prints ``pidlab: error: ...`` and
    exits 2, for every command, whether it runs as the ``pidlab`` executable or in a test's
    ``CliRunner``.
    """

    def main(  # type: ignore[override]
        self,
        args: Sequence[str] | None = None,
        prog_name: str | None = None,
        complete_var: str | None = None,
        standalone_mode: bool = True,
        **extra: Any,
    ) -> Any:
        """Run the command line; in standalone mode, exit with the command's code."""
        _plain_help(self)
        if not standalone_mode:
            return super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        try:
            with sigterm_interrupts():
                code = super().main(args, prog_name, complete_var, standalone_mode=False, **extra)
        except _click.NoArgsIsHelpError:
            code = EXIT_BAD_INPUT  # the help was printed
        except _click.ClickException as exc:
            typer.echo(f"pidlab: error: {usage_message(exc)}", err=True)
            code = exc.exit_code
        except PidlabError as exc:  # one raised outside a command's friendly_errors
            typer.echo(f"pidlab: error: {cli_message(exc)}", err=True)
            code = EXIT_BAD_INPUT
        except (typer.Abort, KeyboardInterrupt):
            typer.echo("pidlab: interrupted", err=True)
            code = EXIT_INTERRUPTED
        sys.exit(code if isinstance(code, int) else 0)


app = typer.Typer(
    cls=PidlabGroup,
    name="pidlab",
    help="MuJoCo models -> linearization -> PID coach -> regions of attraction -> coached RL.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)

F = TypeVar("F", bound=Callable[..., Any])


def _fail(message: str) -> NoReturn:
    """The error's one line (a line break inside a value is shown escaped) and exit code 2."""
    message = message.replace("\r", "\\r").replace("\n", "\\n")
    typer.echo(f"pidlab: error: {message}", err=True)
    raise typer.Exit(code=EXIT_BAD_INPUT)


FLAGS = {"env_id": "ENV", "roa_samples": "--samples", "conditions_file": "--conditions-file",
         "recipe_files": "--recipe", "condition_names": "--conditions", "horizon_s": "--horizon",
         "slice_vars": "--slice", "action_fraction": "--fraction"}  # fmt: skip
"""Python parameter of the API -> the flag that sets it, where the flag is not ``--`` + the name with
dashes (a parameter of the running command itself is found by :func:`flag_of`)."""


def _command_params() -> list[Any]:
    """The Click parameters of the running command (none outside a command)."""
    ctx = get_current_context(silent=True)
    return list(ctx.command.params) if ctx is not None else []


def flag_of(param: str) -> str:
    """The flag (or argument) that sets the Python parameter ``param``, as the error line names it.

    :data:`FLAGS` first (the API's names, e.g. ``horizon_s`` -> ``--horizon``), then an option of
    the running command whose Python name is ``param`` (``resume_dir`` -> ``--resume``), else
    ``--`` + the name with dashes.
    """
    if param in FLAGS:
        return FLAGS[param]
    for p in _command_params():
        if p.name == param:
            opts = [o for o in getattr(p, "opts", []) if o.startswith("-")]
            return max(opts, key=len) if opts else str(getattr(p, "metavar", None) or param.upper())
    return "--" + param.replace("_", "-")


def cli_message(exc: PidlabError) -> str:
    """The error's message as the command line says it: the Python parameter becomes its flag."""
    message = str(exc)
    param = exc.param
    if param and message.startswith(f"{param}="):
        message = f"{flag_of(param)} {message[len(param) + 1 :]}"
    return message


def _refuse_empty_values() -> None:
    """One line and exit 2 when an option or argument was given as ``''`` (or blank), for every command.

    An empty value never means "the default" (``--run-dir ''`` would write into the current folder,
    ``--variables ''`` take the default variables): to get the default, leave the option out.
    """
    from pidlab.checks import shown

    ctx = get_current_context(silent=True)
    for p in _command_params():
        value = ctx.params.get(p.name) if ctx is not None else None
        for v in value if isinstance(value, (list, tuple)) else (value,):
            if isinstance(v, str) and not v.strip():
                optional = any(o.startswith("-") for o in getattr(p, "opts", []))
                why = " (leave the option out for its default)" if optional else ""
                _fail(f"{flag_of(p.name)} {shown(v)}: empty; expected a value{why}")


def _refuse_unused(ctx: typer.Context, names: Sequence[str], why: str) -> None:
    """One line and exit 2 when the command line set one of ``names``, options this call would ignore."""
    for name in names:
        source = ctx.get_parameter_source(name)
        if getattr(source, "name", None) == "COMMANDLINE":
            _fail(f"{flag_of(name)}: {why}")


def friendly_errors(func: F) -> F:
    """Turn :class:`PidlabError` (bad input) into one line and exit code 2, an interrupt into 130."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            _refuse_empty_values()
            return func(*args, **kwargs)
        except PidlabError as exc:
            _fail(cli_message(exc))
        except KeyboardInterrupt:
            typer.echo("pidlab: interrupted", err=True)
            raise typer.Exit(code=EXIT_INTERRUPTED) from None
        except OSError as exc:  # a full disk or quota wherever a command writes: one line, not a traceback
            if exc.errno not in (errno.ENOSPC, errno.EDQUOT):
                raise
            where = f" writing {exc.filename}" if exc.filename else ""
            _fail(f"{os.strerror(exc.errno).lower()}{where}; free some space and run the command again")

    return wrapper  # type: ignore[return-value]


def _vector(text: str | None, what: str) -> list[float] | None:
    from pidlab.checks import parse_vector

    return None if text is None else parse_vector(text, what)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"pidlab {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version and exit.")
    ] = False,
    gym_packages: Annotated[
        str | None,
        typer.Option(
            "--gym-packages",
            metavar="MODULE[,MODULE...]",
            help="Modules to import first: they register your own envs (PIDLAB_GYM_PACKAGES does the same).",
        ),
    ] = None,
) -> None:
    """pidlab: a PID coach for RL agents on MuJoCo models.

    In a folder holding pidlab.toml (pidlab init writes it), its settings apply first.
    """
    from pidlab.errors import PidlabError
    from pidlab.project import apply_project, find_project, load_project

    try:
        project = find_project()
        if project is not None:
            apply_project(load_project(project))
        if gym_packages is not None:
            from pidlab.plant.envs import add_gym_packages

            add_gym_packages(_names(gym_packages, "gym_packages", what="module names"))
    except PidlabError as exc:
        _fail(str(exc))


def _env_arg(text: str) -> str:
    """The env id an ENV argument names; ``module:EnvId`` imports ``module`` first.

    The module is added to :func:`pidlab.plant.envs.add_gym_packages`, so the processes the
    command starts import it too.
    """
    from pidlab.plant.envs import resolve_env_id

    return resolve_env_id(text, remember=True)


def _trainable_env_arg(text: str) -> str:
    """:func:`_env_arg` for the commands that train: an MJCF file or a card-only robot is refused."""
    from pidlab.plant.envs import check_trainable

    return check_trainable(_env_arg(text))


@app.command()
@friendly_errors
def init(
    mjcf: Annotated[str, typer.Argument(metavar="MJCF", help="Your robot's MJCF file (.xml).")],
    env_id: Annotated[
        str, typer.Option("--env-id", metavar="ID", help="The env id to register it as, e.g. MyCartPole-v0.")
    ],
    keyframe: Annotated[
        str | None,
        typer.Option(metavar="NAME", help="Keyframe of the operating point (default: the first; qpos0)."),
    ] = None,
    frame_skip: Annotated[
        int | None,
        typer.Option(
            "--frame-skip",
            metavar="N",
            help="MuJoCo steps per control period (default: the period nearest 20 ms).",
        ),
    ] = None,
    out: Annotated[
        str, typer.Option(metavar="DIR", help="Where to write the scaffold (a project folder).")
    ] = ".",
    force: Annotated[bool, typer.Option("--force", help="Overwrite the scaffold's files.")] = False,
) -> None:
    """Scaffold your own robot: a model card, a recipe, an env module and a project file, to edit.

    Writes DIR/models/ID.toml (its [model] table names the MJCF where it is), DIR/coach/ID.toml,
    DIR/<id>_env.py (registers ID) and DIR/pidlab.toml (pidlab commands run in DIR find them all),
    then prints what to run next. Existing files are kept unless --force.
    """
    import shlex
    from pathlib import Path

    from pidlab.plant.scaffold import scaffold, write_scaffold

    s = scaffold(mjcf, env_id, keyframe, frame_skip, out)
    written = write_scaffold(s, out, force=force)
    for p in written:
        typer.echo(f"wrote {p}")
    here = Path(out).resolve() == Path.cwd().resolve()
    cd = "" if here else f"cd {shlex.quote(str(Path(out).resolve()))}; "
    typer.echo(
        f"next: edit the termination limits in the card, then, in that folder:\n"
        f"  {cd}pidlab linearize {env_id}; pidlab tune {env_id} --auto; pidlab run {env_id}"
    )


@app.command()
@friendly_errors
def linearize(
    target: Annotated[
        str,
        typer.Argument(
            metavar="ENV_OR_MJCF",
            help="A Gymnasium MuJoCo env id (e.g. InvertedPendulum-v5) or the path of an MJCF file.",
        ),
    ],
    at: Annotated[
        str | None,
        typer.Option(
            "--at",
            metavar="KEYFRAME|qpos0|card",
            help="Operating point: a keyframe name, qpos0, or card (the env's model card; the "
            "default when the env has one).",
        ),
    ] = None,
    qpos: Annotated[str | None, typer.Option(help="Explicit qpos, comma-separated (nq values).")] = None,
    qvel: Annotated[str | None, typer.Option(help="Explicit qvel, comma-separated (nv values).")] = None,
    ctrl: Annotated[str | None, typer.Option(help="Explicit ctrl, comma-separated (nu values).")] = None,
    equilibrium_ctrl: Annotated[
        bool,
        typer.Option(
            "--equilibrium-ctrl",
            help="Use the control found by inverse dynamics (mj_inverse + actuator moments).",
        ),
    ] = False,
    settle_joints: Annotated[
        str | None,
        typer.Option(
            "--settle",
            metavar="JOINT,...",
            help="Move these hinge/slide joints (e.g. rootz,rooty) until contacts carry the model, "
            "then use the inverse-dynamics control.",
        ),
    ] = None,
    discrete: Annotated[
        bool, typer.Option("--discrete", help="Show the discrete-time model at the env's control period.")
    ] = False,
    discretization: Annotated[
        str, typer.Option(help="Discrete model: 'step' (differentiate frame_skip MuJoCo steps) or 'zoh'.")
    ] = "step",
    eps: Annotated[float, typer.Option(help="Finite-difference step.")] = 1e-6,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON for machines.")] = False,
    progress: Annotated[
        bool,
        typer.Option(
            "--progress",
            help="Progress bars on stderr (always shown when stderr is a terminal; otherwise a model "
            f"that takes over {LONG_WORK_S:g} s gets an estimate line first).",
        ),
    ] = False,
) -> None:
    """Linearize a MuJoCo model: named A/B tables, eigenvalues, controllability.

    Models of up to 1000 states (2 nv + na) are analyzed (one SVD per mode: minutes for hundreds).
    """
    from pidlab.linear.linearize import check_arguments
    from pidlab.linear.linearize import linearize as run_linearize
    from pidlab.linear.lti import analyze_lti
    from pidlab.linear.serialize import linearization_to_dict
    from pidlab.plant.model import load_model
    from pidlab.report.console import linearization_view, wide_console

    check_arguments(eps, discretization)  # before the model loads
    loaded = load_model(target)
    _check_linearize_size(loaded, discretization, progress)
    vectors = {"qpos": _vector(qpos, "qpos"), "qvel": _vector(qvel, "qvel"), "ctrl": _vector(ctrl, "ctrl")}
    op = _operating_point(loaded, at, vectors, equilibrium_ctrl, settle_joints)
    with _progress_bars(progress) as bar:
        lin = run_linearize(loaded, op, eps=eps, discretization=discretization,  # type: ignore[arg-type]
                            progress=bar("finite differences"))  # fmt: skip
        report_c, report_d = (analyze_lti(lin.sys, progress=bar("modes of the continuous model")),
                              analyze_lti(lin.sysd, progress=bar("modes of the discrete model")))  # fmt: skip
    if as_json:
        typer.echo(json.dumps(linearization_to_dict(lin, report_c, report_d), indent=2))
        return
    wide_console().print(linearization_view(lin, report_d if discrete else report_c, discrete))


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def _check_linearize_size(loaded: Any, discretization: str, progress: bool) -> None:
    """Refuse a model without state or too large to analyze; say how long a large one will take."""
    from pidlab.linear.linearize import check_has_state, estimate_seconds

    check_has_state(loaded)
    m = loaded.model
    n = 2 * m.nv + m.na
    if n > MAX_LINEARIZE_STATES:
        _fail(
            f"{loaded.source}: {n} states (2 nv + na) is more than pidlab linearize analyzes "
            f"({MAX_LINEARIZE_STATES}): the controllability test of every mode would take hours; "
            "the Python function pidlab.linearize gives the matrices alone"
        )
    if _show_progress(progress):
        return
    seconds = estimate_seconds(loaded, discretization)
    if seconds > LONG_WORK_S:
        typer.echo(
            f"pidlab: {loaded.name} has {n} states: linearizing and analyzing it takes about "
            f"{_duration(seconds)} (--progress shows a bar)",
            err=True,
        )


def _show_progress(progress: bool) -> bool:
    """Whether to draw progress bars: ``--progress`` was given, or stderr is a terminal."""
    return progress or sys.stderr.isatty()


@contextlib.contextmanager
def _progress_bars(progress: bool) -> Iterator[Callable[[str], Callable[[int, int], None] | None]]:
    """Progress bars on stderr: yields ``bar(description)``, a ``callback(done, total)`` or None.

    Shown when ``progress`` is True (``--progress``: drawn even into a file or pipe) or stderr is
    a terminal; the bars vanish when the work is done.
    """
    if not _show_progress(progress):
        yield lambda _description: None
        return
    from rich.console import Console

    from pidlab.report.console import progress_bar

    with progress_bar(Console(stderr=True, force_terminal=progress or None), transient=True) as bars:

        def bar(description: str) -> Callable[[int, int], None]:
            task = bars.add_task(description, total=None)
            return lambda done, total: bars.update(task, completed=done, total=total)

        yield bar


def _operating_point(
    loaded: Any, at: str | None, vectors: dict[str, Any], equilibrium_ctrl: bool, settle_joints: str | None
) -> Any:
    """``linearize``'s operating point: ``--at`` with explicit vectors, then ``--settle`` if given."""
    from pidlab.plant.operating_point import resolve_operating_point, settle

    op = resolve_operating_point(loaded, at, **vectors, equilibrium_ctrl=equilibrium_ctrl)
    if settle_joints:
        free = _names(settle_joints, "settle_joints")
        settled = settle(loaded, op.qpos, free)
        base = op.source
        op = resolve_operating_point(loaded, at, qpos=settled.qpos, qvel=op.qvel, equilibrium_ctrl=True)
        op = dataclasses.replace(op, source=f"{base}+settled {'/'.join(free)}")
    return op


AUTO_ONLY = ("bandwidth", "phase_margin", "preset", "output", "name", "workers", "force")
"""``tune`` options that only ``--auto`` uses."""
UI_ONLY = ("spec", "port", "tuning_dir", "animation", "bounds_samples", "allow_host")
"""``tune`` options that only ``--ui`` uses."""


@app.command()
@friendly_errors
def tune(
    ctx: typer.Context,
    env: Annotated[
        str,
        typer.Argument(metavar="ENV", help="An env id with a card (InvertedPendulum-v5, module:EnvId)."),
    ],
    auto: Annotated[bool, typer.Option("--auto", help="Tune automatically and write the spec.")] = False,
    ui: Annotated[bool, typer.Option("--ui", help="Serve the interactive tuner in the browser.")] = False,
    spec: Annotated[
        str | None,
        typer.Option(help="--ui: the spec to start from (default: tuning/ENV.pidlab-robust.toml)."),
    ] = None,
    port: Annotated[int, typer.Option(help="--ui: local port to serve on.")] = 5006,
    tuning_dir: Annotated[
        str, typer.Option(help="--ui: where Save writes ENV.NAME.toml and Load looks; it must exist.")
    ] = "tuning",
    animation: Annotated[
        str, typer.Option(help="--ui: rollout frames: auto, mujoco (offscreen OpenGL) or schematic.")
    ] = "auto",
    bounds_samples: Annotated[
        int, typer.Option(help="--ui: simulated states certifying the region behind Derive bounds.")
    ] = 1000,
    allow_host: Annotated[
        list[str] | None,
        typer.Option(
            "--allow-host",
            metavar="NAME",
            help="--ui: also answer to this host name (repeatable; * for any). By default the tuner "
            "answers only to localhost and 127.0.0.1.",
        ),
    ] = None,
    bandwidth: Annotated[float | None, typer.Option(help="Target gain crossover, rad/s.")] = None,
    phase_margin: Annotated[float | None, typer.Option(help="Target phase margin, degrees.")] = None,
    preset: Annotated[
        str,
        typer.Option(
            help="robust, weak, room (pendulums: the largest rescue region; Hopper, Walker2d: the gains "
            "that hold the most perturbed starts of the model card), or balance (a robot on its feet: "
            "full-state LQR about the card's [balance] posture)."
        ),
    ] = "robust",
    output: Annotated[str | None, typer.Option("-o", "--output", help="Spec file to write (TOML).")] = None,
    name: Annotated[
        str | None, typer.Option(help="--auto: the spec's name (default: pidlab-PRESET).")
    ] = None,
    workers: Annotated[int | None, typer.Option(help="--auto: worker processes (default: cores).")] = None,
    force: Annotated[
        bool, typer.Option("--force", help="--auto: replace the output spec if it exists (with its bounds).")
    ] = False,
) -> None:
    """Tune a PID coach for ENV: automatically (--auto) or interactively in the browser (--ui)."""
    from pidlab.controller.autotune import check_request
    from pidlab.controller.spec import writing_spec
    from pidlab.plant.model import load_model
    from pidlab.report.console import wide_console

    env = _env_arg(env)
    _check_tune_mode(ctx, auto, ui, preset)
    if ui:
        _tune_ui(env, spec, port, tuning_dir, (animation, bounds_samples, allow_host or []))
        return
    from pidlab.checks import check_name

    spec_name = check_name(name, "--name", PidlabError) if name is not None else f"pidlab-{preset}"
    loaded = load_model(env)
    env = loaded.env_id or env  # an MJCF file that a card names: the card's env id
    out = output or f"tuning/{env}.{spec_name}.toml"
    if preset not in ("room", "balance"):
        check_request(loaded, bandwidth, phase_margin, preset)  # bad targets first, then the file
    with writing_spec(out, force=force, param="output") as write:  # refused before the tuning, not after
        result = _auto_tune(loaded, preset, bandwidth, phase_margin, workers)
        path = write(dataclasses.replace(result.spec, name=spec_name))
    _print_tuned(env, preset, result)
    wide_console().print(f"wrote {path}")


def _auto_tune(
    loaded: Any, preset: str, bandwidth: float | None, phase_margin: float | None, workers: int | None
) -> Any:
    """``tune --auto``: the tuning itself, with a progress line."""
    from pidlab.controller.autotune import tune as run_tune
    from pidlab.report.console import progress_bar

    with progress_bar(transient=True, disable=not sys.stdout.isatty()) as bar:
        task = bar.add_task(f"tuning {loaded.name} ({preset})", total=None)
        tick = lambda n: bar.update(task, completed=n)  # noqa: E731
        if preset == "room":
            from pidlab.region.room import tune_for_room

            return tune_for_room(loaded, workers=workers, progress=tick)
        if preset == "balance":
            from pidlab.controller.balance import tune_balance

            return tune_balance(loaded)
        return run_tune(
            loaded, bandwidth=bandwidth, phase_margin=phase_margin, preset=preset, progress=tick,
            workers=workers,
        )  # fmt: skip


def _check_tune_mode(ctx: typer.Context, auto: bool, ui: bool, preset: str) -> None:
    """``tune``: exactly one of ``--auto`` and ``--ui``, and no option the chosen one would ignore."""
    from pidlab.controller.autotune import PRESETS

    if auto == ui:
        _fail("give exactly one of --auto (write a tuned spec) or --ui (interactive tuner in the browser)")
    if ui:
        _refuse_unused(ctx, AUTO_ONLY, "a setting of --auto; the tuner in the browser (--ui) does not use it")
        return
    _refuse_unused(ctx, UI_ONLY, "a setting of the tuner in the browser (--ui); --auto does not use it")
    if preset not in (*PRESETS, "room", "balance"):
        _fail(f"--preset {preset!r}: expected {', '.join(PRESETS)}, room or balance")
    if preset == "room":
        why = "--preset room chooses the gains by the states its coach rescues, not by a crossover or margin"
        _refuse_unused(ctx, ("bandwidth", "phase_margin"), why + " target; expected no target with it")
    if preset == "balance":
        why = "--preset balance is a full-state LQR design about a posture, with no crossover or margin"
        _refuse_unused(ctx, ("bandwidth", "phase_margin"), why + " target; expected no target with it")
        _refuse_unused(ctx, ("workers",), "--preset balance runs no simulations in parallel; expected it "
                       "without --workers")  # fmt: skip


def _print_tuned(env: str, preset: str, result: Any) -> None:
    """``tune --auto``: what was asked and achieved (rad/s, degrees)."""
    from rich.text import Text

    from pidlab.report.console import wide_console

    con = wide_console()
    con.print(Text.assemble((str(env), "bold"), f" {preset} coach: {result.evaluations} evaluations"))
    con.print(
        f"  gain crossover (rad/s): asked {_asked(result.asked_bandwidth, '.4g')}, "
        f"achieved {result.achieved_bandwidth:.4g}"
    )
    con.print(
        f"  phase margin (deg):     asked {_asked(result.asked_phase_margin, '.1f')}, "
        f"achieved {result.achieved_phase_margin:.1f}"
    )
    con.print(f"  Ms: {result.achieved_ms:.3g}; closed-loop spectral radius {result.spectral_radius:.5f}")
    if result.refined_return is not None:
        con.print(
            f"  refined on the real env: mean return {result.refined_return:.1f} on tuning seeds 1000-1002"
        )
    prov = result.spec.provenance
    if prov.get("room_held_share") is not None:
        con.print(
            f"  searched on the real env: holds {prov['room_held_share']:.0%} of {prov['room_starts']} "
            f"perturbed starts for {prov['room_horizon_s']:g} s (`pidlab recovery` measures it on others)"
        )
    if prov.get("balance_posture_qpos") is not None:
        con.print(
            f"  posture: qpos {', '.join(f'{v:.4g}' for v in prov['balance_posture_qpos'])} (centre of mass "
            f"{prov['balance_com_offset_m'] * 1000:.2g} mm off the feet's middle); LQR closed-loop spectral "
            f"radius {prov['balance_lqr_spectral_radius']:.5f} (`pidlab recovery` measures it in MuJoCo)"
        )


def _asked(value: float, fmt: str) -> str:
    """A tuning target as asked, or "nothing" (the room preset asks for no crossover or margin)."""
    return format(value, fmt) if np.isfinite(value) else "nothing"


def _tune_ui(
    env: str, spec_file: str | None, port: int, tuning_dir: str, options: tuple[str, int, list[str]]
) -> None:
    """``tune --ui``: check everything, then serve until interrupted (exit 130, as every command)."""
    from pathlib import Path

    from pidlab.app.serve import check_hosts, check_tuning_dir, serve_tuner
    from pidlab.checks import MAX_SAMPLES, clip, is_file
    from pidlab.controller.spec import load_spec, validate_against
    from pidlab.experiment.conditions import spec_path
    from pidlab.plant.model import load_model

    animation, bounds_samples, allow_host = options
    check_hosts(allow_host)
    if animation not in ("auto", "mujoco", "schematic"):
        _fail(f"--animation {animation!r}: expected auto, mujoco or schematic")
    if not 1 <= bounds_samples <= MAX_SAMPLES:
        _fail(f"--bounds-samples {bounds_samples}: expected 1 to {MAX_SAMPLES:,} simulated states")
    loaded = load_model(env)
    if loaded.card is None:
        _fail(f"{env}: the tuner needs a model card; none found ({loaded.card_hint})")
    env = loaded.env_id or env  # an MJCF file that a card names: the card's env id
    path = Path(spec_file) if spec_file else spec_path(env, "pidlab-robust")
    if not is_file(path):
        _fail(
            f"--spec {clip(str(path))}: no such file; give a coach spec, "
            f"or make one with pidlab tune {env} --auto"
        )
    coach = load_spec(path)
    if coach.env_id != env:
        _fail(f"--spec {path}: a coach for {coach.env_id}, not {env}")
    card = loaded.require_card()
    validate_against(coach, card.observation_names, loaded.input_names, where=str(path))
    folder = check_tuning_dir(tuning_dir)
    serve_tuner(
        coach,
        str(path),
        folder,
        port,
        animation=animation,
        bounds_samples=bounds_samples,
        announce=typer.echo,
        allow_hosts=allow_host,
    )


@app.command()
@friendly_errors
def analyze(
    spec_file: Annotated[str, typer.Argument(metavar="FILE", help="A coach spec (TOML).")],
    plots: Annotated[str | None, typer.Option(metavar="DIR", help="Write PNG plots to DIR.")] = None,
    episodes: Annotated[
        int, typer.Option(help="Coach-alone episodes on the real env, 0 (skip) to 10,000.")
    ] = 10,
    progress: Annotated[
        bool,
        typer.Option("--progress", help="A progress bar on stderr (always shown when stderr is a terminal)."),
    ] = False,
) -> None:
    """Analyze a coach: margins, poles, responses, and its score alone on the real env."""
    from pidlab.controller.analysis import analyze_coach
    from pidlab.controller.balance import design_linearization
    from pidlab.controller.pid import Coach
    from pidlab.controller.rollout import MAX_EPISODES, coach_alone
    from pidlab.controller.spec import load_spec
    from pidlab.files import check_output_folder
    from pidlab.plant.model import load_model
    from pidlab.report.console import analysis_view, wide_console

    if episodes < 0:
        _fail(f"--episodes {episodes}: expected 0 or more (0 skips the episodes)")
    if episodes > MAX_EPISODES:
        _fail(f"--episodes {episodes}: expected at most {MAX_EPISODES:,}; more would run for hours")
    if plots:
        check_output_folder(plots, "plots")
    spec = load_spec(spec_file)
    loaded = load_model(spec.env_id)
    coach = Coach(spec, loaded)
    result = analyze_coach(coach, loaded, design_linearization(spec, loaded))
    score = None
    if episodes:
        with _progress_bars(progress) as bar:
            score = coach_alone(spec, loaded, episodes=episodes, progress=bar("coach-alone episodes"))
    con = wide_console()
    con.print(analysis_view(result, score))
    if plots:
        from pidlab.report.plots import write_plots

        written = write_plots(result, coach, plots)
        con.print(f"wrote {len(written)} plots to {plots}")


_METHOD_HELP = (
    "The region: 'lyapunov' (a level set certified by simulation; on a robot with contacts, "
    "about a balance coach's posture) or 'simulation' (a recoverable box). Default: the model card's."
)


def _check_method(method: str | None) -> None:
    """``--method``: one of the region kinds, refused in one line before any work."""
    from pidlab.region.roa import METHODS

    if method is not None and method not in METHODS:
        _fail(f"--method {method}: expected one of {', '.join(METHODS)}")


@app.command()
@friendly_errors
def roa(
    ctx: typer.Context,
    spec_file: Annotated[str, typer.Argument(metavar="SPEC", help="A coach spec (TOML).")],
    samples: Annotated[int, typer.Option(help="Simulated initial states in the final check (N).")] = 1000,
    seed: Annotated[int, typer.Option(help="Sampling seed.")] = 0,
    horizon: Annotated[float, typer.Option(help="Simulated time per trajectory, s.")] = 3.0,
    plots: Annotated[
        str | None, typer.Option(metavar="DIR", help="Write the slice and phase portrait as PNG.")
    ] = None,
    slice_vars: Annotated[
        str | None,
        typer.Option("--slice", help="Two observation variables for the plots (default: first loop)."),
    ] = None,
    workers: Annotated[
        int | None, typer.Option(help="Worker processes for the simulations (default: the machine's cores).")
    ] = None,
    method: Annotated[str | None, typer.Option(help=_METHOD_HELP)] = None,
) -> None:
    """Estimate and certify the coach's region of attraction (Lyapunov + MuJoCo simulation)."""
    from pidlab.controller.spec import load_spec
    from pidlab.plant.model import load_model
    from pidlab.region.roa import estimate_roa
    from pidlab.report.console import roa_view, wide_console

    if samples < 1:
        _fail(f"--samples {samples}: expected a positive number")
    _check_method(method)
    if not horizon > 0:
        _fail(f"--horizon {horizon}: expected a positive time in s")
    if plots:
        from pidlab.files import check_output_folder

        check_output_folder(plots, "plots")
    else:
        _refuse_unused(ctx, ("slice_vars",), "names the plots' two variables; expected --plots DIR with it")
    spec = load_spec(spec_file)
    loaded = load_model(spec.env_id)
    units = {v.name: v.unit for v in loaded.require_card().observation}
    pair = _slice_pair(spec, loaded, slice_vars, method) if plots else None
    result, kept = estimate_roa(
        spec,
        loaded,
        samples=samples,
        seed=seed,
        horizon_s=horizon,
        keep_trajectories=80 if pair else 0,
        record=pair,
        workers=workers,
        method=method,
    )
    con = wide_console()
    con.print(roa_view(result, units))
    if plots and pair is not None:
        folder = _write_roa_plots(spec, loaded, (result, kept, method), pair, units, horizon, plots)
        con.print(f"wrote 2 plots to {folder}")


def _slice_pair(spec: Any, loaded: Any, slice_vars: str | None, method: str | None) -> tuple[str, str]:
    """``roa --slice``: two observation variables (default: the first loop's signal and rate).

    Checked before the estimate: about a posture, both must be among the level set's variables.
    """
    from pidlab.region.roa import check_portrait_variables

    lp0 = spec.loops[0]
    chosen = _names(slice_vars, "slice_vars") if slice_vars else [lp0.signal, lp0.rate_signal or ""]
    if len(chosen) != 2 or not all(chosen):
        _fail("--slice: expected two observation variables, e.g. --slice hinge_pos,hinge_vel")
    pair = (chosen[0], chosen[1])
    check_portrait_variables(spec, loaded, pair, method, param="slice_vars")
    return pair


def _portrait_extent(result: Any, pair: tuple[str, str]) -> tuple[float, float]:
    """Half-widths of the phase portrait: twice the region's extent along each variable."""
    if result.lyapunov is not None:
        L = result.lyapunov
        P_inv = np.linalg.inv(L.P_y)
        ext = [
            2 * float(np.sqrt(result.level * P_inv[L.variables.index(v)][L.variables.index(v)]))
            if v in L.variables
            else 0.1
            for v in pair
        ]
    else:
        ext = [2 * result.box.get(v, 0.1) for v in pair]
    return (ext[0], ext[1])


def _write_roa_plots(
    spec: Any,
    loaded: Any,
    estimate: tuple[Any, Any, str | None],
    pair: tuple[str, str],
    units: dict[str, str],
    horizon: float,
    plots: str,
) -> Any:
    """``roa --plots``: the region's slice and the coached phase portrait as PNG; returns the folder."""
    from pidlab.files import make_folder, save_figure
    from pidlab.region.roa import phase_portrait
    from pidlab.report.plots import plot_phase_portrait, plot_roa_slice

    result, kept, method = estimate
    folder = make_folder(plots, "plots")
    fig = plot_roa_slice(result, pair, kept, units)
    save_figure(fig, folder / f"roa_{pair[0]}_{pair[1]}.png")
    extent = _portrait_extent(result, pair)
    paths = phase_portrait(spec, loaded, pair, extent, horizon_s=horizon, method=method)
    fig = plot_phase_portrait(
        paths, pair, units, f"{spec.env_id} / {spec.name}: coached phase portrait (MuJoCo)"
    )
    save_figure(fig, folder / f"phase_{pair[0]}_{pair[1]}.png")
    return folder


@app.command()
@friendly_errors
def bounds(
    spec_file: Annotated[str, typer.Argument(metavar="SPEC", help="A coach spec (TOML).")],
    variables: Annotated[
        str | None, typer.Option(help="Box variables, comma-separated (observation names).")
    ] = None,
    write: Annotated[
        bool, typer.Option("--write", help="Write the bounds into the spec's bounds table.")
    ] = False,
    samples: Annotated[
        int, typer.Option(help="Simulated initial states in the region's final check.")
    ] = 1000,
    seed: Annotated[int, typer.Option(help="Sampling seed.")] = 0,
    workers: Annotated[
        int | None, typer.Option(help="Worker processes for the simulations (default: the machine's cores).")
    ] = None,
    method: Annotated[str | None, typer.Option(help=_METHOD_HELP)] = None,
) -> None:
    """Derive critical-state bounds (ellipsoid and box) from the certified region."""
    from pidlab.controller.spec import editing_spec

    if samples < 1:
        _fail(f"--samples {samples}: expected a positive number")
    _check_method(method)
    # --write: the spec is read under its lock, held to its rewrite (a second writer is refused)
    with editing_spec(spec_file, write) as spec:
        _bounds_of(spec, spec_file, variables, write, (samples, seed, workers, method))


def _bounds_of(
    spec: Any,
    spec_file: str,
    variables: str | None,
    write: bool,
    how: tuple[int, int, int | None, str | None],
) -> None:
    """``bounds``: the region and bounds of ``spec``, shown, and written into ``spec_file`` with ``write``."""
    from pidlab.controller.spec import save_spec
    from pidlab.plant.model import load_model
    from pidlab.region.bounds import check_variables, derive_bounds, with_bounds
    from pidlab.region.roa import estimate_roa
    from pidlab.report.console import bounds_view, roa_view, wide_console

    samples, seed, workers, method = how
    loaded = load_model(spec.env_id)
    names = None if variables is None else _names(variables, "variables")
    if names:
        check_variables(names, loaded)
    result, _ = estimate_roa(spec, loaded, samples=samples, seed=seed, workers=workers, method=method)
    crit = derive_bounds(result, spec, loaded, variables=names, seed=seed, workers=workers)
    con = wide_console()
    card = loaded.require_card()
    con.print(roa_view(result, {v.name: v.unit for v in card.observation}))
    con.print(bounds_view(crit))
    if write:
        path = save_spec(with_bounds(spec, crit), spec_file)
        kept = " (its rescue region and takeover choice kept)" if "rescue" in (spec.bounds or {}) else ""
        con.print(f"wrote the bounds into {path}{kept}")


@app.command()
@friendly_errors
def rescue(
    spec_file: Annotated[str, typer.Argument(metavar="SPEC", help="A coach spec (TOML).")],
    trigger: Annotated[
        str,
        typer.Option(help="predictive (the trigger vets each agent action) or reactive (checks after it)."),
    ] = "predictive",
    fraction: Annotated[
        float | None,
        typer.Option(
            help="reactive: the agent step's size, a fraction of the action range in (0, 1] "
            "(default: the full range if the coach handles it, else the largest it does)."
        ),
    ] = None,
    validation: Annotated[int, typer.Option(help="Fresh states per validation draw.")] = 2000,
    coverage: Annotated[int, typer.Option(help="Fresh states over the domain for the coverage.")] = 2000,
    probes: Annotated[
        int, typer.Option(help="Random probes per cell (after its vertices at each guard corner).")
    ] = 2,
    horizon: Annotated[float, typer.Option(help="Simulated time per rescue, s.")] = 3.0,
    seed: Annotated[int, typer.Option(help="Sampling seed.")] = 0,
    write: Annotated[
        bool, typer.Option("--write", help="Write the region into the spec as its takeover region.")
    ] = False,
    plots: Annotated[str | None, typer.Option(help="Folder for the region's figure (PNG).")] = None,
    workers: Annotated[
        int | None, typer.Option(help="Worker processes for the simulations (default: the machine's cores).")
    ] = None,
) -> None:
    """Estimate the coach's rescue region by simulation, validate it and score its coverage."""
    from dataclasses import replace

    from pidlab.controller.spec import editing_spec, save_spec
    from pidlab.files import check_output_folder
    from pidlab.plant.model import load_model
    from pidlab.region.rescue import default_settings, estimate_rescue, with_rescue
    from pidlab.report.console import rescue_view, wide_console

    if trigger not in ("predictive", "reactive"):
        _fail(f"--trigger {trigger!r}: expected predictive or reactive")
    if fraction is not None and not 0.0 < fraction <= 1.0:
        _fail(f"--fraction {fraction}: expected a fraction of the action range in (0, 1]")
    if fraction is not None and trigger == "predictive":
        _fail("--fraction: the predictive trigger vets the agent's action itself and needs no room for it; "
              "use it with --trigger reactive")  # fmt: skip
    if plots:
        check_output_folder(plots, "plots")
    # --write: the spec is read under its lock, held to its rewrite (a second writer is refused)
    with editing_spec(spec_file, write) as spec:
        loaded = load_model(spec.env_id)
        settings = replace(
            default_settings(spec, loaded, trigger), action_fraction=fraction, validation=validation,
            coverage=coverage, probes=probes, horizon_s=horizon, seed=seed,
        )  # fmt: skip
        con = wide_console()
        with _journal_beside(con, spec_file, "rescue-labels") as journal:
            region = _with_bar("rescue region", lambda progress: estimate_rescue(
                spec, loaded, settings, workers=workers, progress=progress, journal=journal))  # fmt: skip
            _said_resumed(con, region.reused, journal)
            units = {v.name: v.unit for v in loaded.require_card().observation}
            con.print(rescue_view(region, units))
            if plots:
                folder = _write_rescue_plot(spec, region, units, plots, write)
                con.print(f"wrote the region's figure to {folder}")
            if write:
                path = save_spec(with_rescue(spec, region), spec_file)
                con.print(f"wrote the rescue region into {path} as its takeover region")


IntoOption = Annotated[
    str,
    typer.Option(
        metavar="core|box",
        help="Where a rescue ends: the certified core (a coach certified by simulation: the horizon held), "
        "or the horizon held and ended in the recoverable box [bounds.box] (upright and slow).",
    ),
]
"""``--into`` of the rescue commands (:data:`pidlab.region.rescue.RESCUE_ENDS`)."""

FocusOption = Annotated[
    int,
    typer.Option(
        help="Further labelled states drawn where a first fit scores like the rescued states, and "
        "fitted on too (0: none); the threshold and the validation stay uniform."
    ),
]
"""``rescue-classifier --focus``."""

NearOption = Annotated[
    int,
    typer.Option(
        help="Further labelled states drawn in boxes about the point the coach hands back at (and the "
        "operating point), 1 % to 50 % of the domain, and fitted on too (0: none): uniform draws over "
        "many variables come near neither."
    ),
]
"""``rescue-classifier --near``."""

FalseClaimsOption = Annotated[
    float,
    typer.Option(
        metavar="RATE",
        help="The failure rate tolerated inside the region, in [0, 0.5): a validation draw is accepted "
        "when its failures show a rate below RATE at 95 % (its failures stay inside). 0: a draw must "
        "have none.",
    ),
]
"""``rescue-classifier --false-claims``."""


@app.command("rescue-classifier")
@friendly_errors
def rescue_classifier(
    spec_file: Annotated[
        str, typer.Argument(metavar="SPEC", help="A coach spec (TOML) with its certified core.")
    ],
    domain: Annotated[
        str,
        typer.Option(
            help="The domain box: VARIABLE=HALF-WIDTH about the operating point, comma-separated "
            "(e.g. slider_pos=0.9,hinge_sin=0.6,hinge2_sin=0.9,slider_vel=1,hinge_vel=2,hinge2_vel=2)."
        ),
    ],
    samples: Annotated[int, typer.Option(help="Labelled states the classifier is fitted on.")] = 160_000,
    calibration: Annotated[int, typer.Option(help="Further labelled states that set its threshold.")] = 25000,
    validation: Annotated[int, typer.Option(help="Fresh states per validation draw.")] = 2000,
    edge_share: Annotated[
        float,
        typer.Option(
            help="The share of the region, its lowest scores, that a second validation draws from: its "
            "edge, where the trigger meets it (0: no edge draw)."
        ),
    ] = 0.05,
    coverage: Annotated[int, typer.Option(help="Fresh states over the domain for the coverage.")] = 20_000,
    focus: FocusOption = 0,
    near: NearOption = 0,
    false_claims: FalseClaimsOption = 0.0,
    width: Annotated[int, typer.Option(help="Units per hidden layer (two hidden layers).")] = 64,
    epochs: Annotated[int, typer.Option(help="Passes over the labelled states.")] = 100,
    horizon: Annotated[float, typer.Option(help="Simulated time per rescue, s.")] = 3.0,
    into: IntoOption = "core",
    seed: Annotated[int, typer.Option(help="Sampling and fitting seed.")] = 0,
    write: Annotated[
        bool, typer.Option("--write", help="Write the region into SPEC as its takeover region.")
    ] = False,
    output: Annotated[
        str | None,
        typer.Option(
            "--output",
            "-o",
            help="Write a copy of SPEC with the region here (named NAME when the file is ENV.NAME.toml).",
        ),
    ] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace an existing --output file.")] = False,
    workers: Annotated[
        int | None, typer.Option(help="Worker processes for the simulations (default: the machine's cores).")
    ] = None,
) -> None:
    """Fit, validate and score a rescue region over every listed variable: a learned classifier."""
    from pidlab.controller.spec import editing_spec, save_spec, writing_spec
    from pidlab.plant.model import load_model
    from pidlab.region.classifier import ClassifierSettings, with_classifier
    from pidlab.report.console import classifier_view, wide_console

    if write and output:
        _fail("--write and --output: choose one (into SPEC, or into a copy)")
    box = _domain_box(domain)
    settings = ClassifierSettings(
        tuple(box), tuple(box.values()), samples=samples, calibration=calibration, validation=validation,
        coverage=coverage, width=width, epochs=epochs, horizon_s=horizon, seed=seed, edge_share=edge_share,
        focus=focus, into=into, near=near, false_claims=false_claims,
    )  # fmt: skip
    copy = writing_spec(output, force=force, param="output") if output else contextlib.nullcontext(None)
    con = wide_console()
    with editing_spec(spec_file, write) as spec, copy as write_copy:
        loaded = load_model(spec.env_id)
        _check_domain_names(box, loaded)
        with _journal_beside(con, output or spec_file, "labels") as journal:  # beside the spec it writes
            found = _resumable_classifier(con, spec, loaded, settings, workers, journal)
            units = {v.name: v.unit for v in loaded.require_card().observation}
            con.print(classifier_view(found, spec.name, spec.env_id, units))
            new = with_classifier(spec, found)
            if write:
                path = save_spec(new, spec_file)
                con.print(f"wrote the classifier region into {path} as its takeover region")
            elif output and write_copy is not None:
                path = write_copy(dataclasses.replace(new, name=_copy_name(spec, output)))
                con.print(f"wrote the spec with its classifier region to {path}")


def _resumable_classifier(
    con: Any, spec: Any, loaded: Any, settings: Any, workers: int | None, journal: Any
) -> Any:
    """:func:`~pidlab.region.classifier.estimate_classifier` with its outcomes kept in ``journal``."""
    from pidlab.region.classifier import estimate_classifier

    found = _with_bar("classifier region", lambda progress: estimate_classifier(
        spec, loaded, settings, workers=workers, progress=progress, journal=journal))  # fmt: skip
    _said_resumed(con, found.reused, journal)
    return found


@contextlib.contextmanager
def _journal_beside(con: Any, spec_file: str, kind: str) -> Iterator[Any]:
    """Where a rescue command keeps its outcomes: ``.NAME.KIND`` beside a spec (None: not writable).

    ``pidlab rescue-classifier`` keeps ``.NAME.labels`` beside the spec it writes, ``pidlab rescue``
    ``.NAME.rescue-labels`` and ``pidlab rescue-coverage`` ``.NAME.coverage-labels`` beside the spec read.

    Each command has its own ``kind`` of folder, so that one never removes another's unfinished
    journal; inside it, a subfolder per coach and setting (:func:`pidlab.region.journal.journal_key`).
    The folder's lock is held while the block runs: a second command on the same journal is
    refused in one line (it would write the same chunk files, and remove them when it ended).
    A block that ends without an error drops the journal (its outcomes are in what the command
    wrote), still under the lock; one stopped or failed keeps it for the same command to resume.
    """
    import os
    from pathlib import Path

    from pidlab.errors import RegionError
    from pidlab.provenance import hold_lock
    from pidlab.region.journal import drop_journal

    path = Path(spec_file)
    folder = path.parent / f".{path.name}.{kind}"
    if not os.access(path.parent, os.W_OK):
        con.print(f"{path.parent} is not writable: no journal is kept, a stopped run starts again")
        yield None
        return
    with hold_lock(folder, RegionError):
        con.print(f"each simulation's outcome is kept in {folder} as it is found: if stopped, the same "
                  "command resumes from them")  # fmt: skip
        yield folder
        drop_journal(folder)


def _said_resumed(con: Any, reused: int, journal: Any) -> None:
    """Say how many outcomes a resumed run read from its journal."""
    if reused:
        con.print(f"resumed: {reused:,} of the simulations were read from {journal}")


def _with_bar(label: str, work: Callable[[Callable[[str, float | None], None]], Any]) -> Any:
    """``work(progress)`` under a transient progress bar that shows its stages.

    Off a terminal (a log file, a pipe) each stage gets one line on stdout as it starts instead, so
    an hour-long estimate run in the background says where it is.
    """
    from pidlab.report.console import progress_bar

    if not sys.stdout.isatty():
        return work(_stage_lines(label))
    with progress_bar(transient=True) as bar:
        task = bar.add_task(label, total=1.0)
        return work(lambda stage, f: bar.update(task, description=stage, completed=f or 0.0))


def _stage_lines(label: str) -> Callable[[str, float | None], None]:
    """A ``progress(stage, fraction)`` that prints ``LABEL: STAGE`` once per new stage, flushed."""
    last = [""]

    def progress(stage: str, fraction: float | None) -> None:
        if stage != last[0]:
            last[0] = stage
            print(f"{label}: {stage}", flush=True)

    return progress


def _check_domain_names(box: dict[str, float], loaded: Any) -> None:
    """Refuse a ``--domain`` variable the env does not observe, before any journal is announced."""
    card = loaded.require_card()
    for name in box:
        card.variable(name)  # UnknownSignalError (one line, exit 2) names the valid ones


def _domain_box(text: str) -> dict[str, float]:
    """``--domain``: ``VARIABLE=HALF-WIDTH`` pairs; a malformed one is refused in one line."""
    import math

    box: dict[str, float] = {}
    for part in _names(text, "domain", what="VARIABLE=HALF-WIDTH pairs"):
        name, sep, value = part.partition("=")
        try:
            half = float(value)
        except ValueError:
            half = math.nan
        if not sep or not name.strip() or not math.isfinite(half) or half <= 0:
            _fail(f"--domain {part!r}: expected VARIABLE=HALF-WIDTH with a half-width > 0")
        if name.strip() in box:
            _fail(f"--domain: {name.strip()!r} is given twice")
        box[name.strip()] = half
    return box


@app.command("rescue-coverage")
@friendly_errors
def rescue_coverage(
    spec_files: Annotated[
        list[str],
        typer.Argument(metavar="SPEC...", help="Coach specs (TOML) of one env, scored on the same states."),
    ],
    domain: Annotated[
        str,
        typer.Option(
            help="The domain box: VARIABLE=HALF-WIDTH about the operating point, comma-separated; the "
            "states the env's termination rule ends, or with a joint outside its range, are dropped."
        ),
    ],
    states: Annotated[int, typer.Option(help="States drawn over the domain and simulated.")] = 2000,
    horizon: Annotated[float, typer.Option(help="Simulated time per rescue, s.")] = 3.0,
    seed: Annotated[int, typer.Option(help="Sampling seed (the same states for every coach).")] = 0,
    into: IntoOption = "core",
    workers: Annotated[
        int | None, typer.Option(help="Worker processes for the simulations (default: the machine's cores).")
    ] = None,
    json_file: Annotated[
        str | None, typer.Option("--json", help="Also write the figures to this JSON file.")
    ] = None,
) -> None:
    """Score each coach's regions over a domain: the rescuable states they hold, and their false claims."""
    from pidlab.files import check_output_file, write_json
    from pidlab.region.coverage import DomainSettings, measure_domain_coverage
    from pidlab.report.console import coverage_view, wide_console

    box = _domain_box(domain)
    settings = DomainSettings(tuple(box), tuple(box.values()), states, horizon, seed, into)
    if json_file is not None:
        check_output_file(json_file, "json")
    specs, loaded = _specs_of_one_env(spec_files)
    _check_domain_names(box, loaded)
    con = wide_console()
    with contextlib.ExitStack() as held:
        journals = [held.enter_context(_journal_beside(con, f, "coverage-labels")) for f in spec_files]
        found = []
        for spec, journal in zip(specs, journals, strict=True):
            work = functools.partial(
                measure_domain_coverage, spec, loaded, settings, workers, journal=journal
            )
            found.append(_with_bar(f"coverage: {spec.name}", work))
            _said_resumed(con, found[-1].reused, journal)
        units = {v.name: v.unit for v in loaded.require_card().observation}
        con.print(coverage_view(found, units))
        if json_file is not None:
            write_json(json_file, [c.to_dict() for c in found])
            con.print(f"wrote {json_file}")


@app.command()
@friendly_errors
def recovery(
    spec_files: Annotated[
        list[str],
        typer.Argument(metavar="SPEC...", help="Coach specs (TOML) of one env, compared side by side."),
    ],
    episodes: Annotated[int, typer.Option(help="Episodes from random perturbed starts, per coach.")] = 100,
    probes: Annotated[int, typer.Option(help="Magnitudes probed per perturbation and side.")] = 20,
    horizon: Annotated[float, typer.Option(help="Seconds the coach must hold a start, s.")] = 5.0,
    seed: Annotated[int, typer.Option(help="Seed of the random starts.")] = 0,
    json_file: Annotated[
        str | None, typer.Option("--json", help="Also write the figures to this JSON file.")
    ] = None,
) -> None:
    """How hard a push each coach alone recovers from: reach per perturbation, falls per 100 episodes."""
    from pidlab.files import check_output_file, write_json
    from pidlab.region.recovery import check_settings, measure_recovery, perturbations_of
    from pidlab.report.console import recovery_view, wide_console

    check_settings(probes, episodes, horizon, seed, ("--probes", "--episodes", "--horizon", "--seed"))
    if json_file is not None:
        check_output_file(json_file, "json")
    specs, loaded = _specs_of_one_env(spec_files)
    per_coach = 2 * len(perturbations_of(loaded)) + episodes
    found = []
    with _counted_bar("recovery", per_coach * len(specs)) as bar:
        for i, spec in enumerate(specs):
            done_before = i * per_coach
            found.append(measure_recovery(
                spec, loaded, probes=probes, episodes=episodes, horizon_s=horizon, seed=seed,
                progress=lambda n: bar(done_before + n),  # noqa: B023 (called before the next spec)
            ))  # fmt: skip
    wide_console().print(recovery_view(found))
    if json_file is not None:
        write_json(json_file, [r.to_dict() for r in found])
        wide_console().print(f"wrote {json_file}")


def _specs_of_one_env(spec_files: list[str]) -> tuple[list[Any], Any]:
    """The coach specs, refused in one line unless they share an env, and that env's model."""
    from pidlab.controller.spec import load_spec
    from pidlab.plant.model import load_model

    specs = [load_spec(f) for f in spec_files]
    envs = sorted({s.env_id for s in specs})
    if len(envs) > 1:
        _fail(f"SPEC...: coaches of {', '.join(envs)}; expected coach specs of one env to compare")
    return specs, load_model(specs[0].env_id)


@contextlib.contextmanager
def _counted_bar(label: str, total: int) -> Iterator[Callable[[int], None]]:
    """A transient progress bar (on a terminal) over ``total`` items; yields ``update(done)``."""
    from pidlab.report.console import progress_bar

    with progress_bar(transient=True, disable=not sys.stdout.isatty()) as bar:
        task = bar.add_task(label, total=total)
        yield lambda done: bar.update(task, completed=done)


ADAPTIVE_HELP = (
    "Margins that depend on the state and the action: a network fitted on this many actions (recorded "
    "before those that set the margins) gives the error's scale, calibrated on those that set them. 0: "
    "constant margins. A classifier region only. Kept in [bounds.forecast]."
)


@app.command()
@friendly_errors
def forecast(
    ctx: typer.Context,
    spec_file: Annotated[
        str, typer.Argument(metavar="SPEC", help="A coach spec (TOML) with a rescue region.")
    ],
    transitions: Annotated[int, typer.Option(help="Actions put to the shield that set the margins.")] = 5000,
    held_out: Annotated[int, typer.Option(help="Further actions that check the margins and vetoes.")] = 5000,
    seed: Annotated[int, typer.Option(help="Seed of the resets, the random agent, the network's fit.")] = 0,
    model: Annotated[
        str,
        typer.Option(
            metavar="linear|learned",
            help="The forecast: the discrete linear model, or that model corrected by a network fitted on "
            "--fit actions recorded first.",
        ),
    ] = "linear",
    fit: Annotated[
        int, typer.Option(help="Actions the learned correction is fitted on (--model learned).")
    ] = 30000,
    width: Annotated[int, typer.Option(help="Units per hidden layer of the learned correction.")] = 64,
    epochs: Annotated[int, typer.Option(help="Passes over the fitted actions.")] = 100,
    bound: Annotated[
        str,
        typer.Option(
            metavar="linear|interval",
            help="How a classifier region's score is bounded over a forecast's margin box: a linear "
            "relaxation of the network (tighter) or interval arithmetic. Kept in [bounds.forecast].",
        ),
    ] = "linear",
    scope: Annotated[
        str,
        typer.Option(
            metavar="domain|all",
            help="Which actions set the margins: those whose forecast lies in the rescue region's domain "
            "box (the only ones whose error can decide a veto), or all. Kept in [bounds.forecast].",
        ),
    ] = "domain",
    pieces: Annotated[int | None, typer.Option(
        help="The most boxes one query of a classifier region bounds at one halving: caps a veto's work (a "
        "box it cannot prove within counts as outside). Default: no cap. Kept in [bounds.forecast].",
    )] = None,
    adaptive: Annotated[int, typer.Option(help=ADAPTIVE_HELP)] = 0,
    write: Annotated[bool, typer.Option("--write", help="Write [bounds.forecast] into SPEC.")] = False,
    output: Annotated[
        str | None,
        typer.Option(
            "--output", "-o",
            help="Write a copy of SPEC with its [bounds.forecast] here "
            "(named NAME when the file is ENV.NAME.toml).",
        ),
    ] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace the --output file if it exists.")] = False,
) -> None:  # fmt: skip
    """Measure the model predictor's forecast error on a spec's rescue region, and its vetoes."""
    from pidlab.controller.spec import editing_spec, save_spec, writing_spec
    from pidlab.plant.model import load_model
    from pidlab.report.console import wide_console
    from pidlab.rl.calibrate import measure_forecast

    if write and output:
        _fail("--write and --output: choose one (into SPEC, or into a copy)")
    _refuse_unused_network(ctx, model, adaptive)
    copy = writing_spec(output, force=force, param="output") if output else contextlib.nullcontext(None)
    with editing_spec(spec_file, write) as spec, copy as write_copy:
        loaded = load_model(spec.env_id)
        recorded = transitions + held_out + (fit if model == "learned" else 0) + max(adaptive, 0)
        with _counted_bar("forecast error", recorded) as bar:
            found = measure_forecast(
                spec, loaded, transitions=transitions, held_out=held_out, seed=seed,
                progress=lambda done, total: bar(done), model=model, fit=fit, width=width, epochs=epochs,
                bound=bound, scope=scope, pieces=pieces, adaptive=adaptive,
            )  # fmt: skip
        con = wide_console()
        con.print(_forecast_view(spec, loaded, found))
        new = _with_forecast(spec, found)
        if write:
            con.print(f"wrote the forecast's error into {save_spec(new, spec_file)}")
        elif output and write_copy is not None:
            path = write_copy(dataclasses.replace(new, name=_copy_name(spec, output)))
            con.print(f"wrote the spec with its forecast's error to {path}")


def _refuse_unused_network(ctx: typer.Context, model: str, adaptive: int) -> None:
    """``forecast``: ``--fit`` only with a learned model, ``--width``/``--epochs`` only with a network."""
    if model != "learned":
        _refuse_unused(ctx, ("fit",), "the actions a learned correction is fitted on; expected it with "
                       "--model learned")  # fmt: skip
        if not adaptive:
            _refuse_unused(ctx, ("width", "epochs"), "sets a network (--model learned or --adaptive N); "
                           "expected it with one of them")  # fmt: skip


def _forecast_view(spec: Any, loaded: Any, found: Any) -> Any:
    """``pidlab forecast``'s view: the error per variable, the vetoes, the share of the region kept."""
    from pidlab.region.forecast import kept_inputs, kept_share
    from pidlab.region.takeover import region_from_bounds
    from pidlab.report.console import forecast_view

    card = loaded.require_card()
    units = {v.name: v.unit for v in card.observation}
    region = region_from_bounds(spec.bounds, card.observation_names, "rescue", spec.name)
    inputs_of = kept_inputs(region, loaded) if found.adaptive is not None else None
    kept = kept_share(region, found.margin, bound=found.bound, pieces=found.pieces, adaptive=found.adaptive,
                      inputs_of=inputs_of)  # fmt: skip
    return forecast_view(found, units, kept)


def _copy_name(spec: Any, output: str) -> str:
    """The name of ``-o FILE``'s copy of ``spec``: NAME for a file ``ENV.NAME.toml``, else the spec's."""
    from pathlib import Path

    stem = Path(output).name.removesuffix(".toml")
    return stem.removeprefix(f"{spec.env_id}.") if stem.startswith(f"{spec.env_id}.") else spec.name


def _with_forecast(spec: Any, found: Any) -> Any:
    """``spec`` with ``found`` as its ``[bounds.forecast]``."""
    return dataclasses.replace(spec, bounds={**(spec.bounds or {}), "forecast": found.to_table()})


def _write_rescue_plot(spec: Any, region: Any, units: dict[str, str], plots: str, write: bool) -> Any:
    """``rescue --plots``: the region with the certified core and the takeover box, as PNG.

    The legend names the takeover region the spec has after the command (the rescue region with
    ``--write``, else the spec's own).
    """
    from pidlab.files import make_folder, save_figure
    from pidlab.region.takeover import takeover_kind
    from pidlab.report.plots import plot_rescue_region

    takeover = "rescue" if write else takeover_kind(spec.bounds) or "none"
    bounds = {**(spec.bounds or {}), "rescue": region.to_table(), "takeover": takeover}
    folder = make_folder(plots, "plots")
    fig = plot_rescue_region(region.grid, bounds, units, f"{spec.env_id} / {spec.name}")
    save_figure(fig, folder / f"rescue_{'_'.join(region.grid.variables)}.png")
    return folder


def _resolve_coach(env: str, coach: str) -> tuple[Any, str | None]:
    """``none``, a spec file, or a spec name in ``tuning/`` (``pidlab-robust``)."""
    from pathlib import Path

    from pidlab.checks import exists, shown
    from pidlab.controller.spec import load_spec
    from pidlab.experiment.conditions import spec_path

    if coach == "none":
        return None, None
    path = Path(coach)
    if not exists(path) and path.suffix != ".toml":
        path = spec_path(env, coach)
    if not exists(path):
        _fail(
            f"--coach {shown(coach)}: expected none, a coach spec file, or the name of a spec in tuning/ "
            f"(e.g. pidlab-robust for tuning/{env}.pidlab-robust.toml)"
        )
    spec = load_spec(path)
    if spec.env_id != env:
        _fail(f"--coach {coach}: the spec is for {spec.env_id}, not for {env}")
    return spec, str(path)


@app.command()
@friendly_errors
def train(
    env: Annotated[
        str, typer.Argument(metavar="ENV", help="A Gymnasium env id with a recipe, e.g. InvertedPendulum-v5.")
    ],
    coach: Annotated[
        str | None,
        typer.Option(
            metavar="SPEC|none",
            help="The coach: a spec file, a spec name in tuning/ (e.g. pidlab-robust), or none.",
        ),
    ] = None,
    recipe_file: Annotated[
        str | None, typer.Option("--recipe", metavar="FILE", help="Recipe (default coach/ENV.toml).")
    ] = None,
    algo: Annotated[str | None, typer.Option(help="ppo or sac (default: the recipe's).")] = None,
    steps: Annotated[
        int | None, typer.Option(help="Budget in env steps, agent + coach (default: the recipe's).")
    ] = None,
    seed: Annotated[int | None, typer.Option(help="Seed (default: the recipe's).")] = None,
    n_envs: Annotated[
        int | None, typer.Option("--n-envs", help="Parallel envs (default: the recipe's).")
    ] = None,
    resume_dir: Annotated[
        str | None,
        typer.Option("--resume", metavar="RUN_DIR", help="Continue this run from its last checkpoint."),
    ] = None,
    run_dir: Annotated[
        str | None,
        typer.Option("--run-dir", metavar="DIR", help="Where to write (default runs/ENV/COACH-ALGO-seedS)."),
    ] = None,
    progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Show a progress bar.")] = True,
) -> None:
    """Train an agent with SB3, coached by a PID coach (or not); evaluate it alone as it learns."""
    from pidlab.report.console import train_view, wide_console
    from pidlab.rl.recipe import default_recipe_path, load_recipe, with_overrides
    from pidlab.rl.rundir import default_run_dir
    from pidlab.rl.train import resume as resume_run
    from pidlab.rl.train import train as run_train

    argv = ["pidlab", *sys.argv[1:]]
    env = _trainable_env_arg(env)
    if resume_dir is not None:
        asked = {"ENV": env, "--algo": algo, "--seed": seed, "--n-envs": n_envs}
        recipe = _resumed_recipe(resume_dir, asked, coach, recipe_file)
        result = resume_run(resume_dir, steps=steps, progress_bar=progress, argv=argv)
    else:
        if coach is None:
            _fail("--coach: required; a spec file, a spec name in tuning/ (e.g. pidlab-robust), or none")
        spec, source = _resolve_coach(env, coach)
        path = recipe_file or str(default_recipe_path(env))
        recipe = load_recipe(path)
        if recipe.env_id != env:
            _fail(f"--recipe {path}: the recipe is for {recipe.env_id}, not for {env}")
        recipe = with_overrides(recipe, algo=algo, steps=steps, seed=seed, n_envs=n_envs)
        folder = run_dir or str(default_run_dir(recipe, spec))
        result = run_train(recipe, spec, folder, coach_source=source, progress_bar=progress, argv=argv)
    wide_console().print(train_view(result, recipe.win.target))
    if not result.completed:
        raise typer.Exit(code=130)


def _resumed_recipe(
    resume_dir: str, asked: dict[str, Any], coach: str | None, recipe_file: str | None
) -> Any:
    """``train --resume``: the run's recipe; a flag given with another value than the run's fails."""
    from pidlab.rl.rundir import load_run_config

    saved, saved_spec, _ = load_run_config(resume_dir)
    env = asked["ENV"]
    given = {"ENV": (env, saved.env_id), "--algo": (asked["--algo"], saved.algo),
             "--seed": (asked["--seed"], saved.seed), "--n-envs": (asked["--n-envs"], saved.n_envs),
             "--coach": (None if coach is None else _resolve_coach(env, coach)[0], saved_spec)}  # fmt: skip
    for flag, (value, had) in given.items():
        if value is not None and value != had:
            shown = getattr(had, "name", had)
            _fail(f"{flag} differs from the run in {resume_dir} ({shown!r}); a resumed run keeps them")
    if coach == "none" and saved_spec is not None:
        _fail(f"--coach none: the run in {resume_dir} was coached by {saved_spec.name}")
    if recipe_file is not None:
        _fail("--recipe: a resumed run keeps the recipe it started with (see its config.toml)")
    return saved


def _names(text: str, param: str, what: str = "names") -> list[str]:
    """Comma-separated names (``--envs a,b``); an empty one (``a,,b``) is refused, not skipped."""
    from pidlab.checks import split_list

    return split_list(text, param, what=what)


def _seed_text(text: str) -> str:
    """``--seeds`` as given, when its digits are 0-9 and no part of a list is empty."""
    from pidlab.checks import check_ascii_digits

    check_ascii_digits(text, "seeds", param="seeds")
    if "," in text:
        _names(text, "seeds", "seeds")
    return text


ReportOnlyOption = Annotated[
    bool, typer.Option("--report-only", help="Write the report from the runs in DIR; train nothing.")
]
StatusOption = Annotated[
    bool,
    typer.Option(
        "--status",
        help="Say how far each run of this experiment is (finished, its checkpoint, its log); train "
        "and write nothing. Safe while the experiment runs.",
    ),
]


@app.command()
@friendly_errors
def experiment(
    envs: Annotated[
        str,
        typer.Option(
            metavar="ENV[,ENV...]", help="Env ids, comma-separated (each needs a recipe in coach/)."
        ),
    ] = "InvertedPendulum-v5",
    conditions: Annotated[
        str,
        typer.Option(
            metavar="NAME[,NAME...]",
            help="Conditions from the conditions file, comma-separated.",
        ),
    ] = "none,paper,pidlab,pidlab-fading",
    seeds: Annotated[
        str, typer.Option(metavar="N|A-B|A,B,...", help="Seeds: a count, a range or a list.")
    ] = "10",
    out: Annotated[
        str | None, typer.Option(metavar="DIR", help="Experiment folder (default results/ENVS).")
    ] = None,
    conditions_file: Annotated[
        str | None,
        typer.Option(
            "--conditions-file", metavar="FILE", help="Conditions file (default coach/conditions.toml)."
        ),
    ] = None,
    recipe: Annotated[
        list[str] | None,
        typer.Option(metavar="FILE", help="A recipe to use instead of coach/ENV.toml (repeatable)."),
    ] = None,
    algo: Annotated[
        str | None, typer.Option(help="ppo or sac for every env (default: each recipe's); a condition "
                                      "naming its own algo (none-sac) keeps it.")
    ] = None,
    steps: Annotated[
        int | None, typer.Option(help="Budget in env steps for every run (default: each recipe's).")
    ] = None,
    backend: Annotated[str, typer.Option(help="process (local pool) or ray.")] = "process",
    address: Annotated[
        str | None, typer.Option(metavar="ADDR", help="Ray cluster address (--backend ray); default: local.")
    ] = None,
    workers: Annotated[
        int | None, typer.Option(help="Runs in parallel (default: the machine's cores).")
    ] = None,
    report_only: ReportOnlyOption = False,
    status: StatusOption = False,
    reuse: Annotated[
        list[str] | None,
        typer.Option(metavar="DIR", help="An earlier experiment: its runs with these settings are copied."),
    ] = None,
    progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Show progress bars.")] = True,
) -> None:
    """Multi-seed coaching experiment: train every (env, condition, seed), then report.

    Killed or interrupted, the same command resumes: finished runs are skipped, unfinished ones
    continue from their last checkpoint. With --reuse, a run that an earlier experiment holds
    finished for the same env, condition, seed and settings is copied instead of trained. With
    --status, the same command says how far its runs are, and changes nothing.
    """
    from pidlab.experiment.sweep import parse_seeds, plan

    env_list = [_trainable_env_arg(e) for e in _names(envs, "envs")]
    folder = out or f"results/{'+'.join(env_list)}"
    p = plan(
        env_list, _names(conditions, "condition_names"), parse_seeds(_seed_text(seeds)), folder,
        conditions_file=conditions_file, recipe_files=recipe or [], algo=algo, steps=steps,
    )  # fmt: skip
    if status:
        return _status(p, report_only, backend, workers, address)
    _check_report_only(p.out, report_only, reuse)
    from pidlab.experiment.sweep import check_sweep, lock_experiment
    from pidlab.report.experiment import write_report

    if not report_only:  # before the lock makes OUT
        check_sweep(p, backend=backend, workers=workers, address=address, reuse=reuse or [])
    with lock_experiment(p):  # held while the runs train and the report is written
        failed = 0 if report_only else _sweep(p, backend, workers, address, progress, reuse or [])
        typer.echo(f"report: {write_report(p, progress_bar=progress)}")
    if failed:
        raise typer.Exit(code=1)


def _status(p: Any, report_only: bool, backend: str, workers: int | None, address: str | None) -> None:
    """``experiment --status``: each run's progress, read from ``p.out``; nothing is written.

    The options of the command it is added to are checked as that command checks them (but
    ``--reuse``, whose folders it does not read).
    """
    from pathlib import Path

    from pidlab.experiment.progress import run_progress
    from pidlab.experiment.sweep import check_backend, check_out_folder
    from pidlab.report.console import status_lines

    if report_only:
        _fail("--status with --report-only: the status writes no report (drop one of them)")
    check_backend(backend, workers, address)
    check_out_folder(p)
    budgets = [int(t.recipe["steps"]) for t in p.tasks]
    rows = [(t.env_id, t.condition, t.seed, b, run_progress(Path(t.run_dir), b))
            for t, b in zip(p.tasks, budgets, strict=True)]  # fmt: skip
    where = p.out if (p.out / "experiment.json").exists() else f"{p.out} (not started: no experiment.json)"
    typer.echo(f"experiment {where}")
    for line in status_lines(rows):
        typer.echo(line)


def _check_report_only(out: Any, report_only: bool, reuse: list[str] | None) -> None:
    """``--report-only`` needs an experiment in ``out`` and copies no run."""
    if report_only and not (out / "experiment.json").exists():
        _fail(f"--report-only: {out} holds no experiment (no experiment.json)")
    if report_only and reuse:
        _fail("--reuse with --report-only: a report copies no run (drop one of them)")


def _sweep(
    p: Any, backend: str, workers: int | None, address: str | None, progress: bool, reuse: list[str]
) -> int:
    """``experiment``: train the plan's runs and say how they went; the number that failed.

    Interrupted, it exits with code 130 (the same command resumes).
    """
    from pidlab.experiment.sweep import run_sweep

    argv = ["pidlab", *sys.argv[1:]]
    result = run_sweep(p, backend=backend, workers=workers, address=address, argv=argv, progress_bar=progress,
                       reuse=reuse)  # fmt: skip
    counts = ", ".join(f"{result.count(s)} {s}" for s in ("done", "skipped", "reused", "stopped", "failed"))
    typer.echo(f"runs: {counts} (of {len(p.tasks)})")
    if result.interrupted:
        typer.echo(
            f"{result.stopped_by or 'interrupted'}: unfinished runs keep their last checkpoint; run the same "
            "command to resume",
            err=True,
        )
        raise typer.Exit(code=130)
    return result.count("failed")


@app.command()
@friendly_errors
def run(
    env: Annotated[
        str,
        typer.Argument(metavar="ENV", help="An env id with a recipe and a card, e.g. InvertedPendulum-v5."),
    ],
    out: Annotated[str | None, typer.Option(metavar="DIR", help="Pipeline folder (default out/ENV).")] = None,
    seeds: Annotated[
        int | None, typer.Option(help="Seeds per condition (default: the recipe's pipeline table).")
    ] = None,
    steps: Annotated[
        int | None, typer.Option(help="Env steps per training run (default: the recipe's pipeline table).")
    ] = None,
    preset: Annotated[
        str | None,
        typer.Option(help="Auto-tuning preset, robust, weak, room or balance (default: the recipe's)."),
    ] = None,
    condition: Annotated[
        str | None,
        typer.Option(
            metavar="NAME",
            help="Condition of coach/conditions.toml whose coaching fields the coached runs use "
            "(default: the recipe's pipeline table).",
        ),
    ] = None,
    samples: Annotated[
        int | None,
        typer.Option(help="Simulated states certifying the region (default: the recipe's roa_samples)."),
    ] = None,
    episodes: Annotated[
        int | None, typer.Option(help="Coach-alone episodes, 0 to skip (default: the recipe's).")
    ] = None,
    workers: Annotated[
        int | None, typer.Option(help="Training runs in parallel (default: the machine's cores).")
    ] = None,
    progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Show progress bars.")] = True,
) -> None:
    """The whole pipeline on ENV: linearize, auto-tune a coach, derive its bounds, train, report.

    Trains the recipe's agent with and without the auto-tuned coach (the pipeline table of its
    recipe sets the seeds and the budget), then writes one report: margins table, region of
    attraction, learning curves, agent-alone scores. Killed or interrupted, the same command
    resumes; other settings need another --out.
    """
    from pidlab.pipeline import run_pipeline, settings_for

    if workers is not None and workers < 1:
        _fail(f"--workers {workers}: expected 1 or more")
    env = _trainable_env_arg(env)
    settings = settings_for(
        env,
        seeds=seeds,
        steps=steps,
        preset=preset,
        roa_samples=samples,
        episodes=episodes,
        condition=condition,
    )
    folder = out or f"out/{env}"
    argv = ["pidlab", *sys.argv[1:]]
    resume = "interrupted: finished stages and runs are kept; run the same command to resume"
    try:
        result = run_pipeline(env, folder, settings, workers=workers, progress_bar=progress, argv=argv)
    except KeyboardInterrupt:  # in a stage before training (a rescue region keeps its simulations)
        typer.echo(resume, err=True)
        raise typer.Exit(code=130) from None
    if result.interrupted:
        typer.echo(resume, err=True)
        raise typer.Exit(code=130)
    typer.echo(f"report: {result.report_html}")
    typer.echo(f"        {result.report_md} (Markdown, figures in {result.out / 'figures'})")
    if result.failed_runs:
        typer.echo(f"{result.failed_runs} training run(s) failed; see {result.out / 'experiment'}", err=True)
        raise typer.Exit(code=1)


def main() -> None:
    """Console entry point.

    Once the command has ended, a further SIGINT or SIGTERM is ignored: it would change nothing,
    and raised while Python shuts down (a weak reference's callback, a thread's exit hook) it
    printed a traceback after the command's last line. A job control that signals the command and
    its process group sends two.
    """
    try:
        app()
    except KeyboardInterrupt:  # pragma: no cover - interactive
        typer.echo("pidlab: interrupted", err=True)
        sys.exit(130)
    finally:
        ignore_stops()


if __name__ == "__main__":  # pragma: no cover
    main()
