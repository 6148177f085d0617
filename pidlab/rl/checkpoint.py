"""An agent's files in a run folder, written and read without pickle.

Run folders travel: published results ship them, sweeps copy them between machines. pidlab
therefore reads nothing from them by unpickling. A checkpoint (and a finished run's final agent)
is stored as:

- ``model.zip``: SB3's own archive, of which pidlab reads only the tensors (``*.pth``, through
  ``torch.load(weights_only=True)``); the pickled ``data`` member that SB3 also writes is never
  read: the agent is rebuilt from the run's recipe and its weights are loaded into it;
- ``vecnormalize.npz``: the observation and return statistics of ``VecNormalize`` (plain arrays,
  read with ``allow_pickle=False``);
- ``replay_buffer.npz`` (off-policy algorithms): the filled part of the replay buffer, plain
  arrays as well; ``coach_buffer.npz`` likewise for the coach's buffer of a coach-buffer run
  (:mod:`pidlab.rl.replay`), and ``proposals.npz`` for the coach's proposals beside the replay
  buffer of a proposer run (:mod:`pidlab.rl.proposer`).

``state.json`` (a checkpoint's) or ``summary.json`` (a finished run's) records each file's
SHA-256 under ``files``; a file whose digest does not match is refused (a damaged checkpoint, from
which a resume falls back), never loaded. Any other file in the folder is ignored.
"""

from __future__ import annotations

import hashlib
import re
import warnings
import zipfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pidlab.errors import CheckpointError
from pidlab.files import open_binary

MODEL = "model.zip"
NORMALIZER = "vecnormalize.npz"
BUFFER = "replay_buffer.npz"
COACH_BUFFER = "coach_buffer.npz"
PROPOSALS = "proposals.npz"
FINAL = {MODEL: "final_model.zip", NORMALIZER: "final_vecnormalize.npz"}
"""A finished run's final agent: the checkpoint file name -> the run folder's file name."""

_HEX = re.compile(r"[0-9a-f]{64}")
_NORMALIZER_SETTINGS = ("clip_obs", "clip_reward", "gamma", "epsilon")
_BUFFER_ARRAYS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


def file_digest(path: Path) -> str:
    """SHA-256 of a file's bytes (hex).

    Raises
    ------
    CheckpointError
        ``path`` is no regular file (a named pipe, a device, a folder) or cannot be read.
    """
    h = hashlib.sha256()
    try:
        with open_binary(path) as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    return h.hexdigest()


def expected_files(off_policy: bool, normalized: bool, coach: bool = False,
                   proposals: bool = False) -> tuple[str, ...]:  # fmt: skip
    """The files of an agent's checkpoint: the model, and its normalizer and buffers if it has them."""
    buffers: tuple[str, ...] = (BUFFER,) if off_policy else ()
    buffers += ((COACH_BUFFER,) if coach else ()) + ((PROPOSALS,) if proposals else ())
    return (MODEL, *((NORMALIZER,) if normalized else ()), *(buffers if off_policy else ()))


def _kinds(model: Any, venv: Any) -> tuple[bool, bool, bool, bool]:
    from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
    from stable_baselines3.common.vec_env import VecNormalize

    coach, proposals = hasattr(model, "coach_buffer"), hasattr(model, "next_proposals")
    return isinstance(model, OffPolicyAlgorithm), isinstance(venv, VecNormalize), coach, proposals


# --------------------------------------------------------------------------- writing


def save_agent(folder: Path, model: Any, venv: Any, buffer: bool = True) -> dict[str, str]:
    """Write the agent's files into ``folder``; return ``{file name: SHA-256}``.

    Parameters
    ----------
    folder : Path
        An existing folder (a checkpoint's, being written).
    model : stable_baselines3.common.base_class.BaseAlgorithm
    venv : VecEnv
        The training envs (their ``VecNormalize`` statistics are saved when there are some).
    buffer : bool
        Whether to save an off-policy agent's replay buffer (and a coach buffer) too.
    """
    model.save(folder / MODEL)
    off_policy, normalized, coach, proposals = _kinds(model, venv)
    names = expected_files(off_policy and buffer, normalized, coach, proposals)
    if NORMALIZER in names:
        _save_arrays(folder / NORMALIZER, normalizer_arrays(venv))
    if BUFFER in names:
        _save_arrays(folder / BUFFER, buffer_arrays(model.replay_buffer))
    if COACH_BUFFER in names:
        _save_arrays(folder / COACH_BUFFER, buffer_arrays(model.coach_buffer))
    if PROPOSALS in names:
        rb = model.replay_buffer
        _save_arrays(folder / PROPOSALS, {"next_proposals": model.next_proposals[: rb.size()]})
    return {name: file_digest(folder / name) for name in names}


def _save_arrays(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    with open(path, "wb") as f:
        np.savez(f, **dict(arrays))  # type: ignore[arg-type]  # numpy's stub types allow_pickle here


def normalizer_arrays(venv: Any) -> dict[str, np.ndarray]:
    """A ``VecNormalize``'s statistics and settings as plain arrays."""
    arrays: dict[str, Any] = {"returns": venv.returns}
    for prefix, rms in (("obs", venv.obs_rms), ("ret", venv.ret_rms)):
        for stat in ("mean", "var", "count"):
            arrays[f"{prefix}_{stat}"] = np.asarray(getattr(rms, stat), dtype=np.float64)
    arrays |= {"norm_obs": np.bool_(venv.norm_obs), "norm_reward": np.bool_(venv.norm_reward)}
    arrays |= {k: np.float64(getattr(venv, k)) for k in _NORMALIZER_SETTINGS}
    return {k: np.asarray(v) for k, v in arrays.items()}


def buffer_arrays(rb: Any) -> dict[str, np.ndarray]:
    """The filled part of an SB3 ``ReplayBuffer`` as plain arrays."""
    size = rb.buffer_size if rb.full else rb.pos
    arrays = {k: getattr(rb, k)[:size] for k in _BUFFER_ARRAYS if getattr(rb, k, None) is not None}
    return {**arrays, "pos": np.int64(rb.pos), "full": np.bool_(rb.full)}


# --------------------------------------------------------------------------- reading


def check_manifest(record: Any, path: Path, names: tuple[str, ...]) -> dict[str, str]:
    """``record["files"]`` checked: exactly ``names``, each with a SHA-256.

    Raises
    ------
    CheckpointError
        Naming ``path`` (the record): no digests (written by a pidlab that pickled its agent's
        files, which pidlab does not load), or other files than ``names``.
    """
    files = record.get("files") if isinstance(record, dict) else None
    if files is None:
        raise CheckpointError(
            f"{path}: records no file digests (written by an earlier pidlab, whose pickled files "
            "pidlab no longer loads)"
        )
    if not isinstance(files, dict) or not all(_is_digest(v) for v in files.values()):
        raise CheckpointError(f"{path}: damaged (files: expected file name -> SHA-256)")
    if sorted(files) != sorted(names):
        raise CheckpointError(f"{path}: damaged (files {sorted(files)}; expected {list(names)} for this run)")
    return dict(files)


def _is_digest(value: Any) -> bool:
    return isinstance(value, str) and _HEX.fullmatch(value) is not None


def check_digest(path: Path, want: str, record: Path) -> None:
    """Refuse a file that is missing or whose SHA-256 is not the one ``record`` holds."""
    if not path.is_file():
        raise CheckpointError(f"{path}: missing")
    if file_digest(path) != want:
        raise CheckpointError(
            f"{path}: damaged (its SHA-256 is not the one {record.name} records); not loaded"
        )


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    try:
        with open_binary(path) as fh, np.load(fh, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except Exception as exc:  # zipfile, numpy and OS errors on a damaged file
        raise CheckpointError(f"{path}: damaged ({short_reason(exc)})") from None


def short_reason(exc: BaseException) -> str:
    """An exception as a short reason on one line (at most 160 characters)."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 160 else text[:157] + "..."


def _like(arrays: dict[str, np.ndarray], key: str, like: Any, path: Path) -> np.ndarray:
    """``arrays[key]``, refused unless it has ``like``'s shape and a finite value of a numeric kind."""
    value = arrays.get(key)
    if value is None or value.shape != np.shape(like) or value.dtype.kind not in "fiub":
        shown = "missing" if value is None else f"shape {value.shape}, dtype {value.dtype}"
        raise CheckpointError(f"{path}: not for these envs ({key}: {shown}; expected shape {np.shape(like)})")
    if value.dtype.kind == "f" and not np.all(np.isfinite(value)):
        raise CheckpointError(f"{path}: damaged ({key} is not finite)")
    return value


def load_normalizer(path: Path, venv: Any) -> None:
    """Set ``venv``'s (a ``VecNormalize``) statistics from ``path``; its settings must agree."""
    a = _read_npz(path)
    for key in (*_NORMALIZER_SETTINGS, "norm_obs", "norm_reward"):
        want = getattr(venv, key)
        got = _like(a, key, np.asarray(want), path)
        if float(got) != float(want):
            raise CheckpointError(f"{path}: not for these envs ({key} = {got}, the recipe's is {want})")
    values = {"returns": _like(a, "returns", venv.returns, path).astype(np.float64)}
    for prefix, rms in (("obs", venv.obs_rms), ("ret", venv.ret_rms)):
        for stat in ("mean", "var", "count"):
            key = f"{prefix}_{stat}"
            values[key] = _like(a, key, getattr(rms, stat), path).astype(np.float64)
        if np.any(values[f"{prefix}_var"] < 0) or values[f"{prefix}_count"] <= 0:
            raise CheckpointError(f"{path}: damaged ({prefix}: a negative variance or no count)")
    for prefix, rms in (("obs", venv.obs_rms), ("ret", venv.ret_rms)):
        rms.mean, rms.var = values[f"{prefix}_mean"], values[f"{prefix}_var"]
        rms.count = float(values[f"{prefix}_count"])
    venv.returns = values["returns"]


def load_buffer(path: Path, rb: Any) -> None:
    """Fill the SB3 ``ReplayBuffer`` ``rb`` (new, of the run's recipe) from ``path``."""
    a = _read_npz(path)
    full = bool(_like(a, "full", np.bool_(False), path))
    pos = int(_like(a, "pos", np.int64(0), path))
    size = rb.buffer_size if full else pos
    if not 0 <= pos < rb.buffer_size:
        raise CheckpointError(f"{path}: damaged (pos = {pos} in a buffer of {rb.buffer_size})")
    for key in _BUFFER_ARRAYS:
        target = getattr(rb, key, None)
        if target is None:
            continue
        value = _like(a, key, target[:size], path)
        if value.dtype != target.dtype:
            raise CheckpointError(
                f"{path}: not for these envs ({key}: dtype {value.dtype}, expected {target.dtype})"
            )
        target[:size] = value
    rb.pos, rb.full = pos, full


def load_weights(path: Path, model: Any) -> None:
    """Load the tensors of SB3's ``model.zip`` into ``model`` (built from the run's recipe).

    Only the archive's ``*.pth`` members are read, with ``torch.load(weights_only=True)``; its
    pickled ``data`` member is not.
    """
    import torch
    from stable_baselines3.common.save_util import load_from_zip_file

    try:
        with zipfile.ZipFile(path) as archive:
            bad = archive.testzip()
        if bad is not None:
            raise CheckpointError(f"{path}: damaged ({bad} in it fails its CRC check)")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            _, params, variables = load_from_zip_file(path, device="cpu", load_data=False)
        model.set_parameters(params, exact_match=True, device="cpu")
        names = model._get_torch_save_params()[1]
        with torch.no_grad():
            for name in names:
                getattr(model, name).copy_((variables or {})[name])  # SAC's entropy coefficient
    except CheckpointError:
        raise
    except Exception as exc:  # zipfile, torch and SB3 raise many kinds on a damaged or foreign file
        raise CheckpointError(f"{path}: damaged or not this run's agent ({short_reason(exc)})") from None


@dataclass(frozen=True)
class LoadedAgent:
    """An agent read back from its files (see :func:`load_agent_files`)."""

    model: Any
    venv: Any


def load_agent_files(
    folder: Path, files: dict[str, str], record: Path, new_model: Callable[[Any], Any], venv: Any,
    names: dict[str, str] | None = None,
) -> LoadedAgent:  # fmt: skip
    """The agent stored in ``folder``: every file checked against its digest, then loaded.

    Parameters
    ----------
    folder : Path
        A checkpoint's folder, or a finished run's.
    files : dict
        ``{file name: SHA-256}`` from the record (:func:`check_manifest`).
    record : Path
        The record that holds the digests (named in messages).
    new_model : callable
        ``new_model(venv)``: a new agent of the run's recipe on ``venv``.
    venv : VecEnv
        New envs of the run's recipe (their normalizer statistics are set).
    names : dict, optional
        Logical file name -> the file's name in ``folder`` (:data:`FINAL` for a final agent).
    """
    names = names or {}
    path = {k: folder / names.get(k, k) for k in files}
    for key, want in files.items():
        check_digest(path[key], want, record)
    if NORMALIZER in files:
        load_normalizer(path[NORMALIZER], venv)
    model = new_model(venv)
    load_weights(path[MODEL], model)
    if BUFFER in files:
        load_buffer(path[BUFFER], model.replay_buffer)
    if COACH_BUFFER in files:
        load_buffer(path[COACH_BUFFER], model.coach_buffer)
    if PROPOSALS in files:
        size = model.replay_buffer.size()
        arrays, where = _read_npz(path[PROPOSALS]), path[PROPOSALS]
        model.next_proposals[:size] = _like(arrays, "next_proposals", model.next_proposals[:size], where)
    return LoadedAgent(model, venv)
