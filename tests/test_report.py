"""The presentation layer: no backend switch at import, plots on given axes, one save_figure, one header."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from matplotlib.figure import Figure

from pidlab.controller.analysis import analyze_coach, closed_loop_responses, loop_responses
from pidlab.controller.pid import Coach
from pidlab.controller.spec import load_spec
from pidlab.files import save_figure
from pidlab.report.experiment import paper_numbers, report_header
from pidlab.report.plots import coach_figures, plot_bode, plot_nyquist, plot_poles, plot_responses
from tests.helpers import TUNING

IP = "InvertedPendulum-v5"


def test_importing_the_report_layer_keeps_the_users_backend(tmp_path):
    png = tmp_path / "a.png"
    code = (
        "import sys, matplotlib\n"
        "matplotlib.use('pdf')\n"
        "import pidlab.report.plots, pidlab.report.curves, pidlab.report.experiment, pidlab.report.pipeline\n"
        "from matplotlib.figure import Figure\n"
        "from pidlab.files import save_figure\n"
        "fig = Figure()\n"
        "fig.subplots().plot([0, 1])\n"
        "save_figure(fig, sys.argv[1])\n"
        "print(matplotlib.get_backend())\n"
    )
    done = subprocess.run([sys.executable, "-c", code, str(png)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "pdf"
    assert png.read_bytes()[:4] == b"\x89PNG"


@pytest.fixture(scope="module")
def paper_coach(models):
    loaded = models[IP]
    coach = Coach(load_spec(TUNING / f"{IP}.paper.toml"), loaded)
    return analyze_coach(coach, loaded), coach


def test_plots_draw_on_the_given_axes_or_on_a_new_figure_outside_pyplot(paper_coach):
    import matplotlib.pyplot as plt

    analysis, coach = paper_coach
    before = plt.get_fignums()
    fig = plot_poles(analysis)
    assert isinstance(fig, Figure) and plt.get_fignums() == before  # a bare Figure: pyplot never saw it
    mine = Figure()
    ax = mine.add_subplot()
    assert plot_poles(analysis, ax=ax) is mine
    assert ax.get_title().endswith("poles (dt = 0.04 s)") and len(ax.lines) == 2
    grid = mine.subplots(1, 2)  # one loop: step and initial deviation side by side
    responses = closed_loop_responses(analysis, coach, horizon_s=1.0)
    assert plot_responses(responses, ax=grid) is mine
    assert all(len(a.lines) == 1 for a in grid)
    with pytest.raises(ValueError, match="expected 2 axes"):
        plot_responses(responses, ax=[ax])
    stems = [stem for stem, _ in coach_figures(analysis, coach)]
    assert stems == ["bode_slide", "nyquist_slide", "poles", "responses"]


def test_bode_and_nyquist_only_draw_the_loop_response_they_are_given(paper_coach):
    analysis, coach = paper_coach
    (response,) = loop_responses(analysis, coach, points=50)
    mine = Figure()
    bode_axes = mine.subplots(2, 1)
    assert plot_bode(response, ax=bode_axes) is mine
    magnitude, phase = bode_axes
    assert magnitude.get_title() == "loop broken at slide"
    assert np.array_equal(magnitude.lines[0].get_xdata(), response.omega)
    assert np.array_equal(magnitude.lines[0].get_ydata(), response.magnitude_db)
    assert np.array_equal(phase.lines[0].get_ydata(), response.phase_deg)
    fig = plot_nyquist(response, title="L")
    nyquist = fig.axes[0]
    assert nyquist.get_title() == "L"
    assert np.array_equal(nyquist.lines[0].get_xdata(), response.response.real)
    assert np.array_equal(nyquist.lines[1].get_ydata(), -response.response.imag)


def test_save_figure_writes_bare_and_pyplot_figures_and_closes_the_latter(tmp_path):
    import matplotlib.pyplot as plt

    bare = Figure()
    bare.subplots().plot(np.arange(3))
    assert save_figure(bare, tmp_path / "sub" / "bare.png").read_bytes()[:4] == b"\x89PNG"
    fig = plt.figure()
    fig.gca().plot(np.arange(3))
    save_figure(fig, tmp_path / "pyplot.png")
    assert not plt.fignum_exists(fig.number)
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["bare.png", "pyplot.png", "sub"]  # no temp files


RECORD = {
    "command": ["pidlab", "experiment", "--seeds", "2"],
    "created": "2026-01-02T03:04:05+0000",
    "git": {"sha": "0123456789abcdef", "dirty": True},
    "resumes": [{}, {}],
    "versions": {"torch": "2.0", "python": "3.11", "platform": "not shown"},
}


def test_one_header_for_both_reports():
    experiment = report_header("Coaching experiment: X", RECORD, scope="Seeds 0..1 (2); conditions none")
    assert experiment == [
        "# Coaching experiment: X",
        "",
        "Command: `pidlab experiment --seeds 2`",
        "",
        "Seeds 0..1 (2); conditions none; created 2026-01-02T03:04:05+0000; git 0123456789ab (dirty); "
        "resumed 2 time(s).",
        "",
        "Versions: python 3.11, torch 2.0.",
        "",
    ]
    pipeline = report_header("pidlab run: X", {"git": {"sha": None}}, notes=["Settings: s."],
                             default_command="pidlab run X")  # fmt: skip
    assert pipeline == [
        "# pidlab run: X",
        "",
        "Command: `pidlab run X`; created ; git ?; resumed 0 time(s).",
        "",
        "Settings: s.",
        "",
        "Versions: .",
        "",
    ]


def test_the_papers_numbers_come_from_the_model_cards():
    paper = paper_numbers(IP)
    assert paper is not None
    assert (paper.win_target, paper.wins_coached, paper.wins_uncoached) == (800, 100, 160)
    assert (paper.average_coached, paper.average_uncoached) == (104, 159)
    assert paper_numbers("NoSuchEnv-v0") is None


def test_the_main_jobs_reason_quotes_the_published_savings():
    from pidlab.report.pipeline import Evidence, evidence_reading

    def row(metric: str, verdict: str, saving: str = "", low: str = "", high: str = "", iqm: str = "0") -> dict:
        return {"metric": metric, "verdict": verdict, "saving": saving, "saving_low": low, "saving_high": high,
                "iqm": iqm, "p_holm": "0.001"}  # fmt: skip

    rows = {
        ("coached", "falls"): row("falls", "better", "1.0", "1.0", "1.0"),
        ("none", "falls"): row("falls", "", iqm="200"),
        ("coached", "env_steps_to_alone_target"): row("env_steps_to_alone_target", "better", "0.75", "0.6", "inf"),
        ("coached", "final_score"): row("final_score", "no clear difference"),
    }
    text = evidence_reading(Evidence("docs/results/X", rows), "coached")
    assert text.startswith("It beats `none` on env steps until the agent alone keeps the target")
    assert "fewer falls during training, IQM 0.0 against 200.0" in text
    assert "Savings of the median against `none` (95 % intervals): falls +100.0 % [+100.0 %, +100.0 %]; " in text
    assert "env steps to the target +75.0 % [+60.0 %, unbounded]" in text
