"""The ``pidlab`` command line.

Every verb is a thin layer over the Python API: parse options, call, print. Bad input
(a :class:`pidlab.errors.PidlabError`) becomes one line on stderr and exit code 2.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import sys
from collections.abc import Callable
from typing import Annotated, Any, TypeVar

import typer

from pidlab import __version__
from pidlab.errors import PidlabError

app = typer.Typer(
    name="pidlab",
    help="MuJoCo models -> linearization -> PID coach -> regions of attraction -> coached RL.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)

F = TypeVar("F", bound=Callable[..., Any])


def _fail(message: str) -> None:
    typer.echo(f"pidlab: error: {message}", err=True)
    raise typer.Exit(code=2)


def friendly_errors(func: F) -> F:
    """Turn :class:`PidlabError` (bad input) into one line on stderr and exit code 2."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except PidlabError as exc:
            _fail(str(exc))

    return wrapper  # type: ignore[return-value]


def _vector(text: str | None, what: str) -> list[float] | None:
    if text is None:
        return None
    try:
        return [float(v) for v in text.replace(";", ",").split(",") if v.strip()]
    except ValueError:
        _fail(f"--{what} {text!r}: expected comma-separated numbers, e.g. --{what} 0,0.1")
    return None


def _version(value: bool) -> None:
    if value:
        typer.echo(f"pidlab {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Print the version and exit.")
    ] = False,
) -> None:
    """pidlab: a PID coach for RL agents on MuJoCo models."""


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
) -> None:
    """Linearize a MuJoCo model: named A/B tables, eigenvalues, controllability."""
    from pidlab.linearize import linearize as run_linearize
    from pidlab.lti import analyze_lti
    from pidlab.model import load_model
    from pidlab.operating_point import resolve_operating_point
    from pidlab.render import linearization_to_dict, linearization_view, wide_console

    if discretization not in ("step", "zoh"):
        _fail(f"--discretization {discretization!r}: expected 'step' or 'zoh'")
    if not eps > 0:
        _fail(f"--eps {eps}: expected a positive step, e.g. 1e-6")
    loaded = load_model(target)
    op = resolve_operating_point(
        loaded,
        at,
        qpos=_vector(qpos, "qpos"),
        qvel=_vector(qvel, "qvel"),
        ctrl=_vector(ctrl, "ctrl"),
        equilibrium_ctrl=equilibrium_ctrl,
    )
    if settle_joints:
        from pidlab.operating_point import settle

        free = [name.strip() for name in settle_joints.split(",") if name.strip()]
        settled = settle(loaded, op.qpos, free)
        base = op.source
        op = resolve_operating_point(loaded, at, qpos=settled.qpos, qvel=op.qvel, equilibrium_ctrl=True)
        op = dataclasses.replace(op, source=f"{base}+settled {'/'.join(free)}")
    lin = run_linearize(loaded, op, eps=eps, discretization=discretization)  # type: ignore[arg-type]
    report_c = analyze_lti(lin.sys)
    report_d = analyze_lti(lin.sysd)
    if as_json:
        typer.echo(json.dumps(linearization_to_dict(lin, report_c, report_d), indent=2))
        return
    wide_console().print(linearization_view(lin, report_d if discrete else report_c, discrete))


def main() -> None:
    """Console entry point."""
    try:
        app()
    except KeyboardInterrupt:  # pragma: no cover - interactive
        typer.echo("pidlab: interrupted", err=True)
        sys.exit(130)


if __name__ == "__main__":  # pragma: no cover
    main()
