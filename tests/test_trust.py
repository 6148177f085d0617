"""Run folders are untrusted: pidlab unpickles nothing from them and refuses files that do not match.

A run folder may come from anywhere (published results ship them, sweeps copy them between
machines). These tests plant files that would run code if they were unpickled (a
``vecnormalize.pkl`` and ``replay_buffer.pkl`` in the latest checkpoint, a pickled member in
``model.zip``'s ``data``, an object array in ``vecnormalize.npz``), with and without a matching
digest in ``state.json``, and check that nothing ran. Files changed after the checkpoint was
written are refused by their digest, and the resume falls back to the previous checkpoint.
"""

from __future__ import annotations

import base64
import hashlib
import io
import json
import pickle
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest

import pidlab
from pidlab.errors import RunDirError
from pidlab.rl.checkpoint import BUFFER, MODEL, NORMALIZER, load_buffer
from pidlab.rl.recipe import load_recipe
from pidlab.rl.rundir import checkpoint_folders, latest_checkpoint
from pidlab.rl.train import train
from tests.helpers import cli_in_process
from tests.test_recovery import tiny_recipe

IP = "InvertedPendulum-v5"


class _Payload:
    """Unpickling this creates the file ``marker``: the proof that a pickle was loaded."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[object, tuple[str]]:
        return (Path.touch, (str(self.marker),))  # type: ignore[return-value]


def _evil(marker: Path) -> bytes:
    return pickle.dumps(_Payload(marker))


def _set_digest(checkpoint: Path, name: str) -> None:
    """What an attacker who also rewrites state.json does: the digest of the planted file."""
    record = checkpoint / "state.json"
    state = json.loads(record.read_text())
    state["files"][name] = hashlib.sha256((checkpoint / name).read_bytes()).hexdigest()
    record.write_text(json.dumps(state))


@pytest.fixture(scope="module")
def prepared(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("trust")
    result = train(load_recipe(tiny_recipe(folder, steps=400)), None, folder / "run", progress_bar=False)
    assert result.completed and len(checkpoint_folders(folder / "run")) == 2
    return folder / "run"


@pytest.fixture
def run(prepared: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(prepared, tmp_path / "run"))


def _resume(run: Path) -> tuple[int, list[str]]:
    code, stderr = cli_in_process("train", IP, "--resume", str(run), "--steps", "600", "--no-progress")
    return code, stderr.strip().splitlines()


def test_a_checkpoint_records_the_digest_of_each_of_its_files(prepared: Path) -> None:
    for checkpoint in checkpoint_folders(prepared):
        files = json.loads((checkpoint / "state.json").read_text())["files"]
        assert sorted(files) == sorted([MODEL, NORMALIZER])
        for name, want in files.items():
            assert hashlib.sha256((checkpoint / name).read_bytes()).hexdigest() == want
        assert not list(checkpoint.glob("*.pkl"))
    assert not list(prepared.glob("*.pkl"))


def test_planted_pickles_are_never_loaded(run: Path, tmp_path: Path) -> None:
    marker = tmp_path / "ran"
    latest = latest_checkpoint(run)
    assert latest is not None
    (latest / "vecnormalize.pkl").write_bytes(_evil(marker))
    (latest / "replay_buffer.pkl").write_bytes(_evil(marker))
    (run / "final_vecnormalize.pkl").write_bytes(_evil(marker))
    code, lines = _resume(run)
    assert code == 0, lines
    assert not marker.exists()
    assert not [ln for ln in lines if "warning" in ln]  # the checkpoint is sound: the extra files are ignored
    entry = json.loads((run / "run.json").read_text())["resumes"][-1]
    assert entry["from_env_steps"] == int(latest.name)


def test_a_pickled_member_in_model_zip_is_not_read_even_with_a_matching_digest(run: Path, tmp_path: Path) -> None:
    marker = tmp_path / "ran"
    latest = latest_checkpoint(run)
    assert latest is not None
    archive = latest / MODEL
    members = {}
    with zipfile.ZipFile(archive) as z:
        for name in z.namelist():
            members[name] = z.read(name)
    data = json.loads(members["data"])
    data["policy_class"] = {":serialized:": base64.b64encode(_evil(marker)).decode()}
    data["evil"] = {":serialized:": base64.b64encode(_evil(marker)).decode()}
    members["data"] = json.dumps(data).encode()
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for name, payload in members.items():
            z.writestr(name, payload)
    archive.write_bytes(buf.getvalue())
    _set_digest(latest, MODEL)
    code, lines = _resume(run)
    assert code == 0, lines
    assert not marker.exists()
    assert json.loads((run / "run.json").read_text())["resumes"][-1]["from_env_steps"] == int(latest.name)


def test_an_object_array_in_the_normalizer_is_refused_and_the_resume_falls_back(run: Path, tmp_path: Path) -> None:
    marker = tmp_path / "ran"
    previous, latest = checkpoint_folders(run)
    with open(latest / NORMALIZER, "wb") as f:
        np.savez(f, obs_mean=np.array([_Payload(marker)], dtype=object))
    _set_digest(latest, NORMALIZER)
    code, lines = _resume(run)
    assert code == 0, lines
    assert not marker.exists()
    warnings = [ln for ln in lines if ln.startswith("pidlab: warning: ")]
    assert len(warnings) == 1 and NORMALIZER in warnings[0], lines
    assert json.loads((run / "run.json").read_text())["resumes"][-1]["from_env_steps"] == int(previous.name)


@pytest.mark.parametrize("name", [MODEL, NORMALIZER])
def test_a_file_changed_after_its_checkpoint_is_refused_by_its_digest(run: Path, name: str) -> None:
    previous, latest = checkpoint_folders(run)
    shutil.copy(previous / name, latest / name)  # a valid file, but not the one the checkpoint wrote
    code, lines = _resume(run)
    assert code == 0, lines
    warnings = [ln for ln in lines if ln.startswith("pidlab: warning: ")]
    assert len(warnings) == 1 and f"{latest / name}" in warnings[0] and "SHA-256" in warnings[0], lines
    entry = json.loads((run / "run.json").read_text())["resumes"][-1]
    assert entry["from_env_steps"] == int(previous.name)
    assert entry["damaged_checkpoints"][0]["env_steps"] == int(latest.name)


def test_checkpoints_without_digests_are_not_loaded_and_nothing_changes(run: Path) -> None:
    from tests.test_recovery import snapshot

    for checkpoint in checkpoint_folders(run):
        record = checkpoint / "state.json"
        state = json.loads(record.read_text())
        del state["files"]
        record.write_text(json.dumps(state))
    before = snapshot(run)
    code, lines = _resume(run)
    assert code == 2 and len(lines) == 1 and lines[0].startswith("pidlab: error: "), lines
    assert "no file digests" in lines[0] and "cannot resume" in lines[0]
    assert snapshot(run) == before


def test_a_checkpoint_folder_without_state_json_is_reported_and_recorded(run: Path) -> None:
    previous, latest = checkpoint_folders(run)
    (latest / "state.json").unlink()
    code, lines = _resume(run)
    assert code == 0, lines
    warnings = [ln for ln in lines if ln.startswith("pidlab: warning: ")]
    assert len(warnings) == 1 and "state.json" in warnings[0], lines
    entry = json.loads((run / "run.json").read_text())["resumes"][-1]
    assert entry["from_env_steps"] == int(previous.name)
    assert entry["damaged_checkpoints"][0]["env_steps"] == int(latest.name)


def test_load_agent_refuses_a_final_model_that_does_not_match(run: Path, tmp_path: Path) -> None:
    shutil.copy(checkpoint_folders(run)[0] / MODEL, run / "final_model.zip")
    with pytest.raises(RunDirError, match="final_model.zip.*SHA-256"):
        pidlab.load_agent(run)
    with pytest.raises(RunDirError, match="not a pidlab run directory"):
        pidlab.load_agent(tmp_path)
    with pytest.raises(RunDirError, match="run_dir"):
        pidlab.load_agent(None)  # type: ignore[arg-type]


def test_the_sac_replay_buffer_round_trips_as_plain_arrays(tmp_path: Path) -> None:
    from tests.test_train import tiny_recipe as train_recipe

    path = train_recipe(tmp_path, algo="sac", steps=300, checkpoint={"every": 300}, evaluation={"every": 300})
    run = tmp_path / "sac"
    result = train(load_recipe(path), None, run, progress_bar=False)
    checkpoint = latest_checkpoint(run)
    assert result.completed and checkpoint is not None
    assert sorted(json.loads((checkpoint / "state.json").read_text())["files"]) == sorted([MODEL, BUFFER])  # [sac] normalizes nothing
    model = pidlab.load_agent(run).model
    load_buffer(checkpoint / BUFFER, model.replay_buffer)
    assert model.replay_buffer.size() == 300
    assert np.all(model.replay_buffer.actions[:300] != 0)
