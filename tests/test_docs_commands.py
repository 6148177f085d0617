"""The newcomer's path: every command of the README, Getting started and the tutorials runs.

The commands are read from the ```bash and ```python blocks of the pages, in order, and run with
tiny budgets (the rewrites are in :data:`TINY`), each page in its own working folder holding a
copy of ``tuning/``. A page whose command fails, or whose command prints a traceback, fails
here: the docs cannot silently rot. ``bash scripts/test.sh`` is the one command not run: it runs
this suite (CI runs it, ``.ci/run``).
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from pidlab.app.browser import free_port

ROOT = Path(__file__).resolve().parents[1]
VENV_BIN = Path(sys.executable).parent
PAGES = ("README.md", "docs/getting-started.md", *sorted(
    str(p.relative_to(ROOT)) for p in (ROOT / "docs" / "tutorials").glob("*.md")
))  # fmt: skip
NOT_RUN = {"bash scripts/test.sh": "runs this test suite; CI runs it"}


def _scaled(value: str) -> str:
    """Budgets in env steps: a fiftieth, at least 400 (so a resumed, longer budget stays longer)."""
    return str(max(400, int(value) // 50))


# per pidlab verb: option -> a value, or a function of the written value; added when absent
TINY: dict[str, dict[str, object]] = {
    "run": {"--seeds": "1", "--steps": "4000", "--samples": "40", "--episodes": "1"},  # demonstrations: 2,500
    "train": {"--steps": _scaled},
    "experiment": {"--steps": _scaled, "--seeds": "1"},
    "roa": {"--samples": "40"},
    "bounds": {"--samples": "40"},
    "analyze": {"--episodes": "1"},
    "rescue": {"--validation": "200", "--coverage": "200"},
}
PYTHON_TINY = (
    (re.compile(r"samples=\d+"), "samples=40"),
    (re.compile(r'"demonstrations": \{"steps": \d+'), '"demonstrations": {"steps": 200'),  # under the tiny budget
)


def blocks(page: str) -> list[tuple[str, str]]:
    """The (language, text) of every ```bash and ```python block of ``page``."""
    text = (ROOT / page).read_text()
    return [(m.group(1), m.group(2)) for m in re.finditer(r"^```(bash|python)\n(.*?)^```", text, re.M | re.S)]


def shell_commands(block: str) -> list[str]:
    """The commands of a bash block: continuation lines joined, comments and blank lines dropped."""
    out, pending = [], ""
    for line in block.splitlines():
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        line = pending + line
        pending = ""
        command = line.split(" #", 1)[0].strip()
        if command and not command.startswith("#"):
            out.append(command)
    return out


def tiny(argv: list[str]) -> list[str]:
    """``argv`` with the budget options of :data:`TINY` replaced or added."""
    verb = (
        argv[1]
        if argv[0] == "pidlab" and len(argv) > 1
        else "run"
        if argv[:2] == ["bash", "scripts/main.sh"]
        else None
    )
    rules = TINY.get(verb or "", {})
    argv = list(argv)
    for option, rule in rules.items():
        if option in argv:
            i = argv.index(option) + 1
            argv[i] = rule(argv[i]) if callable(rule) else str(rule)
        elif not callable(rule):
            argv += [option, str(rule)]
    return argv


def _env() -> dict[str, str]:
    return {**os.environ, "PATH": f"{VENV_BIN}{os.pathsep}{os.environ.get('PATH', '')}", "COLUMNS": "120"}


def serve_ui(argv: list[str], cwd: Path, env: dict[str, str] | None = None) -> None:
    """Start the tuner, fetch its page, stop it with SIGTERM: it must shut down cleanly (exit 130)."""
    port = str(free_port())
    if "--port" in argv:
        argv[argv.index("--port") + 1] = port
    else:
        argv += ["--port", port]
    proc = subprocess.Popen(
        argv, cwd=cwd, env=env or _env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        deadline, page = time.monotonic() + 120, ""
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=30) as r:
                    page = r.read().decode()
                break
            except OSError:
                time.sleep(0.5)
        assert "<html" in page.lower(), f"{' '.join(argv)}: no page served (exit {proc.poll()})"
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    # SIGTERM stops the server like Ctrl-C: exit code 130, its workers shut down, no traceback
    assert proc.returncode == 130, err[-2000:]
    assert "Traceback" not in err, err[-2000:]


_MAIN_JOB: dict[tuple[str, ...], Path] = {}


def _main_job(options: list[str], cwd: Path, what: str) -> None:
    """``bash scripts/main.sh`` (from the repo, into ``cwd``); run once per session per option set.

    README and Getting started show the same command; it is self-contained (it writes only its
    own folder), so its second appearance checks the first run's report instead of rerunning it.
    The folder it is given (``--out``) is no new setting: with the tiny budgets, Getting started's
    ``--seeds 1 --steps 10000 --out out/quick`` is the README's command too.
    """
    key = _without_out(options)
    if key not in _MAIN_JOB or not (_MAIN_JOB[key] / "report.html").is_file():
        out = cwd / "main-out"
        argv = ["bash", str(ROOT / "scripts" / "main.sh"), *options, "--out", str(out)]
        done = subprocess.run(argv, env=_env(), capture_output=True, text=True, timeout=900)
        _check(done, what)
        assert f"report: {out / 'report.html'}" in done.stdout
        _the_main_job_warm_starts_with_the_recipes_condition(out)
        _MAIN_JOB[key] = out
    assert (_MAIN_JOB[key] / "report.html").is_file() and (_MAIN_JOB[key] / "report.md").is_file()


def _the_main_job_warm_starts_with_the_recipes_condition(out: Path) -> None:
    """The recipe's condition: the coach demonstrates, the agent is cloned, the report cites its evidence."""
    import json

    from pidlab.rl.recipe import load_pipeline_settings

    settings = load_pipeline_settings(ROOT / "coach" / "InvertedPendulum-v5.toml")
    run = out / "experiment" / "runs" / "InvertedPendulum-v5" / "coached" / "seed-0"
    record = json.loads((run / "warm_start.json").read_text())
    summary = json.loads((run / "summary.json").read_text())
    assert record["demonstration_steps"] == 2500 and summary["kept_rounds"] >= 1
    assert summary["env_steps"] == summary["agent_steps"] + summary["coach_steps"] >= 4000
    report = (out / "report.md").read_text()
    assert f"condition `{settings.condition}`" in report
    assert "docs/results/InvertedPendulum-v5-teach4" in report  # its confirmation, on seeds 110-119


def _without_out(options: list[str]) -> tuple[str, ...]:
    """``options`` without ``--out DIR``, in a fixed order (the settings of a pipeline)."""
    pairs, rest = {}, list(options)
    while rest:
        flag = rest.pop(0)
        value = rest.pop(0) if rest and not rest[0].startswith("--") else ""
        if flag != "--out":
            pairs[flag] = value
    return tuple(f"{k}={v}" for k, v in sorted(pairs.items()))


def _check(done: subprocess.CompletedProcess[str], what: str) -> None:
    assert done.returncode == 0, (
        f"{what}: exit {done.returncode}\n{done.stdout[-1500:]}\n{done.stderr[-3000:]}"
    )
    assert "Traceback" not in done.stderr, f"{what}:\n{done.stderr[-3000:]}"


def run_page(page: str, cwd: Path) -> int:
    """Run every command of ``page`` in ``cwd``; returns how many ran."""
    ran = 0
    for lang, text in blocks(page):
        if lang == "python":
            for pattern, repl in PYTHON_TINY:
                text = pattern.sub(repl, text)
            done = subprocess.run([sys.executable, "-c", text], cwd=cwd, env=_env(), capture_output=True,
                                  text=True, timeout=600)  # fmt: skip
            _check(done, f"{page}: python block\n{text}")
            ran += 1
            continue
        for command in shell_commands(text):
            if command in NOT_RUN:
                continue
            argv = tiny(shlex.split(command))
            if argv[:2] == ["bash", "scripts/main.sh"]:
                _main_job(argv[2:], cwd, f"{page}: {command}")
            elif argv[0] == "pidlab" and "--ui" in argv:
                serve_ui(argv, cwd)
            else:
                done = subprocess.run(argv, cwd=cwd, env=_env(), capture_output=True, text=True, timeout=900)
                _check(done, f"{page}: {' '.join(argv)}")
            ran += 1
    return ran


def test_pages_have_commands_and_only_known_ones():
    for page in PAGES:
        for lang, text in blocks(page):
            if lang != "bash":
                continue
            for command in shell_commands(text):
                head = shlex.split(command)[:2]
                assert head[0] == "pidlab" or head in (
                    ["bash", "scripts/main.sh"],
                    ["bash", "scripts/test.sh"],
                ), f"{page}: {command!r} is neither a pidlab command nor one of the two scripts"
    assert any("bash scripts/main.sh" in t for _, t in blocks("README.md"))
    assert any("bash scripts/test.sh" in t for _, t in blocks("README.md"))
    assert len(PAGES) == 7


def test_tiny_rewrites():
    assert tiny(["pidlab", "train", "X", "--steps", "30000"]) == ["pidlab", "train", "X", "--steps", "600"]
    assert tiny(["pidlab", "roa", "s.toml"]) == ["pidlab", "roa", "s.toml", "--samples", "40"]
    assert tiny(["bash", "scripts/main.sh"])[2:4] == ["--seeds", "1"]
    assert shell_commands("a \\\n  b # c\n# d\n\ne") == ["a    b", "e"]


@pytest.mark.parametrize("page", PAGES)
def test_every_command_of_the_page_runs(page, tmp_path):
    shutil.copytree(ROOT / "tuning", tmp_path / "tuning")
    assert run_page(page, tmp_path) > 0
