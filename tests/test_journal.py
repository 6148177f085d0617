"""The labels' journal: outcomes kept as they are found, and a stopped estimate resumed from them."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pidlab.controller.spec import load_spec
from pidlab.errors import RegionError
from pidlab.plant.model import load_model
from pidlab.region import rescue
from pidlab.region.classifier import ClassifierSettings, estimate_classifier
from pidlab.region.journal import LabelJournal, journal_key, start_key
from pidlab.region.rescue import outcome_facts
from tests.helpers import TUNING, cli_in_process

IP = "InvertedPendulum-v5"
SPEC = TUNING / f"{IP}.pidlab-rescue.toml"
SETTINGS = ClassifierSettings(
    ("hinge_pos", "slider_pos", "hinge_vel", "slider_vel"), (0.2, 1.0, 4.0, 1.5), samples=3000,
    calibration=1000, validation=100, coverage=200, width=16, epochs=60, seed=1, edge_share=0.0,
)  # fmt: skip


def _outcome(ok: bool, k: float) -> tuple[bool, np.ndarray]:
    return ok, np.array([k, -k, 0.0])


def test_outcomes_are_found_again_after_a_reopen_and_bad_chunks_are_left_out(tmp_path) -> None:
    folder = tmp_path / "labels" / "abc"
    journal = LabelJournal(folder)
    assert len(journal) == 0 and not folder.exists()  # nothing written before the first outcome
    x0, x1 = np.array([0.0, 0.1]), np.array([0.0, 0.2])
    starts = [(x0, None), (x1, None), (x0, np.array([0.5]))]
    journal.record(starts, [_outcome(True, 1.0), _outcome(False, 2.0), _outcome(False, 3.0)])
    journal.record([(x1, np.array([0.5]))], [_outcome(True, 4.0)])
    again = LabelJournal(folder)
    assert len(again) == again.loaded == 4 and not again.skipped
    ok, obs = again.get((x0, np.array([0.5])))
    assert not ok and obs.tolist() == [3.0, -3.0, 0.0]  # the kicked start is its own
    assert again.get((x0, None))[0] and not again.get((x1, None))[0]
    assert again.get((np.array([0.0, 0.3]), None)) is None
    assert start_key(x0, None) != start_key(x1, None)
    (folder / "chunk-000002.npz").write_bytes(b"cut short")
    (folder / "chunk-000003.npz.tmp").write_bytes(b"a write that never finished")
    cut = LabelJournal(folder)
    assert len(cut) == 3 and cut.skipped and cut.skipped[0].startswith("chunk-000002.npz")
    cut.record([(x1, np.array([0.5]))], [_outcome(True, 4.0)])  # a new chunk does not overwrite an old one
    assert sorted(p.name for p in folder.glob("chunk-*.npz")) == [
        "chunk-000001.npz", "chunk-000002.npz", "chunk-000003.npz"
    ]  # fmt: skip
    assert len(LabelJournal(folder)) == 4
    cut.remove()
    assert not folder.exists() and not folder.parent.exists()


def test_a_file_where_the_journal_goes_is_refused(tmp_path) -> None:
    (tmp_path / "labels").write_text("not a folder")
    with pytest.raises(RegionError, match="labels: the labels' journal must be a folder"):
        LabelJournal(tmp_path / "labels" / "abc")


def test_the_journal_is_named_by_what_decides_an_outcome() -> None:
    import dataclasses

    spec, loaded = load_spec(SPEC), load_model(IP)
    base = journal_key(outcome_facts(spec, loaded, 75, False))
    assert base == journal_key(outcome_facts(spec, load_model(IP), 75, False))  # loaded again: the same
    assert base != journal_key(outcome_facts(spec, loaded, 76, False))  # another horizon
    assert base != journal_key(outcome_facts(spec, loaded, 75, True))  # starts on the floor
    other = load_spec(TUNING / f"{IP}.pidlab-robust.toml")
    assert base != journal_key(outcome_facts(other, loaded, 75, False))  # another coach
    heavier = load_model(IP)
    heavier.model.body_mass[1] *= 1.5  # an edited MJCF file compiles to another model
    assert base != journal_key(outcome_facts(spec, heavier, 75, False))
    skipped = dataclasses.replace(loaded, frame_skip=loaded.frame_skip + 1)
    assert base != journal_key(outcome_facts(spec, skipped, 75, False))


class _Stop(Exception):
    pass


def test_a_stopped_estimate_resumes_from_its_journal_to_the_same_region(tmp_path, monkeypatch) -> None:
    spec, loaded = load_spec(SPEC), load_model(IP)
    plain = estimate_classifier(spec, loaded, SETTINGS, workers=1)
    monkeypatch.setattr(rescue, "CHUNK", 500)  # a chunk written every 500 simulations

    def stop_midway(stage: str, fraction: float | None) -> None:
        if stage == "labelling" and fraction is not None and fraction > 0.6:
            raise _Stop

    journal = tmp_path / "labels"
    with pytest.raises(_Stop):
        estimate_classifier(spec, loaded, SETTINGS, workers=1, progress=stop_midway, journal=journal)
    kept = len(LabelJournal(next(journal.iterdir())))
    assert 500 <= kept < SETTINGS.samples + SETTINGS.calibration  # whole chunks, not the unfinished one
    resumed = estimate_classifier(spec, loaded, SETTINGS, workers=2, journal=journal)
    assert resumed == plain and resumed.reused == kept  # the same region, the kept outcomes not simulated
    assert resumed.provenance["simulations"] == plain.provenance["simulations"]
    assert all(np.array_equal(a[0], b[0]) for a, b in zip(resumed.classifier.layers, plain.classifier.layers,
                                                         strict=True))  # fmt: skip


def test_the_command_keeps_its_journal_beside_the_spec_and_removes_it_once_written(tmp_path) -> None:
    out = tmp_path / f"{IP}.mine.toml"
    (tmp_path / f".{out.name}.labels").write_text("a file in the journal's place")
    code, err = cli_in_process(
        "rescue-classifier", str(SPEC), "--domain", "hinge_pos=0.2,slider_pos=1,hinge_vel=4,slider_vel=1.5",
        "--samples", "3000", "--calibration", "1000", "--validation", "100", "--coverage", "200",
        "--width", "16", "--epochs", "60", "--seed", "1", "--edge-share", "0", "--workers", "1", "-o", str(out),
    )  # fmt: skip
    assert code == 2 and "the labels' journal must be a folder; move that file away" in err
    assert len(err.strip().splitlines()) == 1 and not out.exists()
    (tmp_path / f".{out.name}.labels").unlink()
    from typer.testing import CliRunner

    from pidlab.cli import app

    done = CliRunner().invoke(app, [
        "rescue-classifier", str(SPEC), "--domain", "hinge_pos=0.2,slider_pos=1,hinge_vel=4,slider_vel=1.5",
        "--samples", "3000", "--calibration", "1000", "--validation", "100", "--coverage", "200",
        "--width", "16", "--epochs", "60", "--seed", "1", "--edge-share", "0", "--workers", "1", "-o", str(out),
    ])  # fmt: skip
    assert done.exit_code == 0, done.stderr
    assert out.exists() and not (tmp_path / f".{out.name}.labels").exists()
    stages = [ln for ln in done.stdout.splitlines() if ln.startswith("classifier region: ")]
    assert len(stages) >= 3 and len(set(stages)) == len(stages)  # off a terminal: one line per stage, in order
    assert any("validation" in ln for ln in stages)


GRID = rescue.RescueSettings(
    ("hinge_pos", "hinge_vel"), (0.2, 2.5), (8, 10), {"slider_pos": 0.05}, "predictive", None,
    probes=1, horizon_s=3.0, validation=150, coverage=150, seed=4,
)  # fmt: skip
"""A small grid estimate of the room coach (its fixture twin is tests/test_rescue.py's ``_small``)."""


def _stopped_at(stage: str, share: float):
    def stop(label: str, fraction: float | None) -> None:
        if label.startswith(stage) and fraction is not None and fraction > share:
            raise _Stop

    return stop


def test_a_stopped_grid_estimate_resumes_from_its_journal_to_the_same_region(tmp_path, monkeypatch) -> None:
    spec, loaded = load_spec(SPEC), load_model(IP)
    plain = rescue.estimate_rescue(spec, loaded, GRID, workers=1)
    monkeypatch.setattr(rescue, "CHUNK", 100)
    journal = tmp_path / "labels"
    with pytest.raises(_Stop):
        rescue.estimate_rescue(spec, loaded, GRID, workers=1, progress=_stopped_at("validation", 0.5),
                               journal=journal)  # fmt: skip
    kept = len(LabelJournal(next(journal.iterdir())))
    assert kept >= 100
    resumed = rescue.estimate_rescue(spec, loaded, GRID, workers=2, journal=journal)
    assert resumed.reused == kept and plain.reused == 0
    assert np.array_equal(resumed.grid.table, plain.grid.table)
    assert resumed.coverage == plain.coverage and resumed.validation == plain.validation
    assert resumed.provenance["simulations"] == plain.provenance["simulations"]


def test_a_stopped_coverage_resumes_from_its_journal_to_the_same_figures(tmp_path, monkeypatch) -> None:
    from pidlab.region.coverage import DomainSettings, measure_domain_coverage

    spec, loaded = load_spec(SPEC), load_model(IP)
    domain = DomainSettings(("hinge_pos", "slider_pos", "hinge_vel", "slider_vel"), (0.2, 1.0, 4.0, 1.5),
                            states=300)  # fmt: skip
    plain = measure_domain_coverage(spec, loaded, domain, workers=1)
    monkeypatch.setattr(rescue, "CHUNK", 100)
    journal = tmp_path / "labels"
    with pytest.raises(_Stop):
        measure_domain_coverage(spec, loaded, domain, workers=1, progress=_stopped_at("labelling", 0.5),
                                journal=journal)  # fmt: skip
    kept = len(LabelJournal(next(journal.iterdir())))
    assert 100 <= kept < 300
    resumed = measure_domain_coverage(spec, loaded, domain, workers=1, journal=journal)
    assert resumed.reused == kept
    figures, again = plain.to_dict(), resumed.to_dict()
    figures.pop("elapsed_s"), again.pop("elapsed_s")
    assert json.dumps(again) == json.dumps(figures) and "reused" not in again  # nan where a region holds none


@pytest.mark.parametrize("command", ["rescue", "rescue-coverage"])
def test_the_rescue_commands_keep_their_own_journal_beside_the_spec_and_remove_it(tmp_path, command) -> None:
    spec = tmp_path / f"{IP}.mine.toml"
    spec.write_text(SPEC.read_text())
    other = tmp_path / f".{spec.name}.labels" / "abc"  # an unfinished rescue-classifier's journal
    other.mkdir(parents=True)
    (other / "chunk-000001.npz").write_bytes(b"kept")
    kind = {"rescue": "rescue-labels", "rescue-coverage": "coverage-labels"}[command]
    (tmp_path / f".{spec.name}.{kind}").write_text("a file in the journal's place")
    args = {
        "rescue": ["--validation", "100", "--coverage", "100", "--probes", "1"],
        "rescue-coverage": ["--domain", "hinge_pos=0.2,hinge_vel=2", "--states", "100"],
    }[command]
    code, err = cli_in_process(command, str(spec), *args, "--workers", "1")
    assert code == 2 and "the labels' journal must be a folder; move that file away" in err
    assert len(err.strip().splitlines()) == 1
    (tmp_path / f".{spec.name}.{kind}").unlink()
    code, err = cli_in_process(command, str(spec), *args, "--workers", "1")
    assert code == 0, err
    assert not (tmp_path / f".{spec.name}.{kind}").exists()
    assert (other / "chunk-000001.npz").read_bytes() == b"kept"  # another command's journal is left alone


def test_a_second_command_on_the_same_journal_is_refused_and_leaves_it(tmp_path) -> None:
    """Two ``rescue-classifier`` writing the same spec shared one journal: each wrote the same chunk
    files, and the first to end removed them. The second is refused in one line, before any work."""
    import subprocess
    import sys

    out = tmp_path / f"{IP}.mine.toml"
    journal = tmp_path / f".{out.name}.labels"
    (journal / "abc").mkdir(parents=True)
    (journal / "abc" / "chunk-000001.npz").write_bytes(b"kept")
    holder = subprocess.Popen(
        [sys.executable, "-c", "import sys, time\nfrom pidlab.errors import RegionError\n"
         "from pidlab.provenance import hold_lock\nwith hold_lock(sys.argv[1], RegionError):\n"
         "    print('held', flush=True)\n    time.sleep(60)\n", str(journal)],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        code, err = cli_in_process(
            "rescue-classifier", str(SPEC), "--domain", "hinge_pos=0.2", "--workers", "1", "-o", str(out)
        )
    finally:
        holder.kill()
        holder.wait()
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert f"{journal}: in use by another pidlab command (pid {holder.pid})" in err
    assert not out.exists() and (journal / "abc" / "chunk-000001.npz").read_bytes() == b"kept"
