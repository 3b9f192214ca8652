"""A study's files: the per-trial checkpoint, the columnar trial table, the rerun recording and the run metadata.

* ``checkpoint.npz`` — the whole engine state after trial t (optimizer and simulator leaves, last context, every
  trial's log, wall time), written to a temporary file and renamed (atomic: a kill leaves the previous one). It
  carries the study's fingerprint and backend; resuming a different study from it, or on another backend, is refused,
  and a damaged one is reported as corrupt with its path (it is read without pickles). With N processes each writes
  the rows of its own instances, ``checkpoint.<rank>of<N>.t<trial>.npz``, and keeps its previous trial's file until
  every process has written the next one; reading merges the newest trial all N wrote (docs/scaling.md).
* ``trials.parquet`` — one row per (instance, trial): instance labels, conditions, the 8 parameters, context, J,
  velocity, CoT, falls. ``pandas.read_parquet(path)`` or ``polars.read_parquet(path)``.
* ``recording.rrd`` — rerun: optimization progress (J, velocity, CoT, context per trial and instance) and each
  group's best gait, full body (``cpgjax.study.scene``: every body and its geoms, the floor at the slope, contact
  forces as arrows, CPG phases and amplitudes).
* ``best_params/<group>.json`` — per group of the study (``studies.gaits.group_name`` of its ``group_by`` labels,
  e.g. ``tegotae``) its best gait, one that walked (``studies.gaits.best_gaits``): its parameters with what they
  were tuned for (:mod:`cpgjax.trial.tuned`), which ``cpgjax deploy --params`` and ``cpgjax walk --params``
  replay, and the trial lengths the study films it with (``best_<group>.mp4``, :mod:`cpgjax.studies.video`).
* ``metadata.json`` — the command line, cpgjax's version and git commit, the optimizer's settings, versions,
  devices, backend, wall time, env-steps/s and real-time factor.

No command writes into a non-empty folder or over a file unless told to (:func:`claim_folder`, :func:`claim_file`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import json
import os
import pathlib
import re
import zipfile
from typing import Any, NamedTuple

import jax
import numpy as np

import cpgjax
from cpgjax import compile_cache, outputs, provenance
from cpgjax.go1 import physics as physics_profiles
from cpgjax.go1 import terrain as terrains
from cpgjax.go1.constants import TICK_S
from cpgjax.optim import bo
from cpgjax.sim import walk
from cpgjax.study import placement as study_placement
from cpgjax.study import rate
from cpgjax.study import scene as study_scene
from cpgjax.study import spec as study_spec
from cpgjax.study.spec import StudyError
from cpgjax.trial import params as param_space
from cpgjax.trial import tuned


class OutputError(RuntimeError):
    """Writing one of a run's files failed; the message says which, what was kept and how to write the rest."""


CHECKPOINT = "checkpoint.npz"
BEST_PARAMS = "best_params"  # a study's folder of best parameters per group
_SHARD = re.compile(r"checkpoint\.(\d+)of(\d+)\.t(\d+)\.npz")
RECORDING = "recording.rrd"
TABLE = "table.md"  # the study's report (cpgjax.studies writes it)


class TrialLog(NamedTuple):
    """What the engine keeps of one trial for every instance (leading axis B)."""

    params: np.ndarray  # (B, 8) proposed parameters, physical units
    context: np.ndarray  # (B, 2) measured [c_load N, c_slope rad]
    objective: np.ndarray  # (B,) J for the trial's target
    velocity_xy_mps: np.ndarray  # (B, 2) steady-phase mean
    cot: np.ndarray  # (B,)
    beta: np.ndarray  # (B,) β of the proposal
    context_changed: np.ndarray  # (B,) whether the proposal used β_init,c
    accepted: np.ndarray  # (B,) the optimizer stored the observation
    roll_std_rad: np.ndarray
    pitch_std_rad: np.ndarray
    saturation_fraction: np.ndarray
    energy_j: np.ndarray
    distance_m: np.ndarray
    total_mass_kg: np.ndarray
    fell: np.ndarray
    failed: np.ndarray
    safety_margin: np.ndarray  # (B,) the trial's worst safety margin (< 0: unsafe; docs/decisions.md §17)
    safe_fallback: np.ndarray  # (B,) --safe: nothing was certified safe, a safe trial's parameters were repeated


def stacked(logs: list[TrialLog], batch_size: int) -> TrialLog:
    """Per-trial logs of the padded batch → one :class:`TrialLog` of (num_trials, B, ...) arrays of its first
    ``batch_size`` rows, the instances (without the padding)."""
    if not logs:
        return TrialLog(*(np.zeros((0, batch_size)) for _ in TrialLog._fields))
    return TrialLog(*(np.stack([np.asarray(f)[:batch_size] for f in field]) for field in zip(*logs, strict=True)))


class Checkpoint(NamedTuple):
    trial: int  # trials completed
    opt_leaves: list  # optimizer-state leaves (instances first)
    sim_leaves: list  # simulator-state leaves (instances first)
    context: np.ndarray  # (B, 2) last measured context
    logs: list  # a TrialLog per completed trial
    wall_s: float
    timing: dict


class Shard(NamedTuple):
    """Which file a process checkpoints to and which instances it holds: rows ``first_row`` … of the study's."""

    rank: int = 0
    num_processes: int = 1
    first_row: int = 0


def shard_path(out_dir, shard: Shard, trial: int) -> pathlib.Path:
    """``checkpoint.npz`` for one process, else ``checkpoint.<rank>of<N>.t<trial>.npz``."""
    if shard.num_processes == 1:
        return pathlib.Path(out_dir) / CHECKPOINT
    return pathlib.Path(out_dir) / f"checkpoint.{shard.rank}of{shard.num_processes}.t{trial:06d}.npz"


def checkpoint_files(out_dir) -> list[pathlib.Path]:
    """Every checkpoint file in ``out_dir`` (one process's and N processes' shards)."""
    out = pathlib.Path(out_dir)
    if not out.is_dir():
        return []
    return sorted(p for p in out.iterdir() if p.name == CHECKPOINT or _SHARD.fullmatch(p.name))


# Fields a study sets only where it uses them; unset (None), they are not part of its definition, so a study without
# them keeps the fingerprint of its other fields (and the checkpoints written before the fields existed resume).
_UNSET_UNLESS_GIVEN = (
    "max_trials",
    "ramp",
    "startup",
    "switches",
    "gaits",
    "terrain_amplitude_m",
    "terrain_seed",
    "foot_friction",
)


def definition(spec) -> dict[str, str]:
    """Each field of the study's definition, as its repr (a checkpoint records them to name what differs); the
    fields of ``_UNSET_UNLESS_GIVEN`` only where they are set."""
    return {
        f.name: repr(getattr(spec, f.name))
        for f in dataclasses.fields(spec)
        if not (f.name in _UNSET_UNLESS_GIVEN and getattr(spec, f.name) is None)
    }


def fingerprint(spec) -> str:
    """A string that changes whenever the study's definition does: the spec's repr, of the fields of
    :func:`definition`."""
    return f"{type(spec).__qualname__}({', '.join(f'{k}={v}' for k, v in definition(spec).items())})"


def extension_of(meta: dict, spec) -> bool:
    """Whether ``spec`` continues the checkpointed run ``meta`` describes with the results of a run of
    ``spec.num_trials``: the definitions differ in ``num_trials`` and ``max_trials`` alone, both give the optimizers
    the same capacity (the GP's arithmetic depends on it), the checkpoint's trials are within ``spec.num_trials``,
    and ``spec`` gives those trials the conditions they were run under.

    Raises:
      StudyError: the definitions differ in those two fields only, but one of the other conditions fails (the
        message says which, and what to run instead).
    """
    theirs = meta.get("definition")
    if not isinstance(theirs, dict) or "num_trials" not in theirs:
        return False
    try:
        ran = dataclasses.replace(
            spec,
            num_trials=int(theirs["num_trials"]),
            max_trials=int(theirs["max_trials"]) if "max_trials" in theirs else None,
        )
    except ValueError:
        return False
    if fingerprint(ran) != meta.get("fingerprint") or ran == spec:
        return False
    capacity, wanted = ran.optimizer_config().capacity, spec.optimizer_config().capacity
    again = "run it afresh in another --out (a run started with --max-trials M can be extended up to M trials)"
    if capacity != wanted:
        how = (
            f"resume with --trials {spec.num_trials} --max-trials {capacity} to continue it as that run"
            if capacity >= spec.num_trials
            else again
        )
        raise StudyError(
            f"--trials {spec.num_trials}: the run in this folder holds {capacity} trials in its "
            f"optimizers (its --max-trials, by default its --trials), and the GP's arithmetic depends "
            f"on it: a run of {spec.num_trials} with room for {wanted} computes every trial otherwise; "
            f"{how}"
        )
    done = int(meta["trial"])
    if done > spec.num_trials:
        raise StudyError(
            f"--trials {spec.num_trials}: the run in this folder has done {done} trials already; "
            f"--resume with --trials {done} or more"
        )
    ran_conditions, conditions = study_spec.conditions(ran), study_spec.conditions(spec)
    for field, values in ran_conditions._asdict().items():
        if not np.array_equal(values[:, :done], getattr(conditions, field)[:, :done]):
            raise StudyError(
                f"--trials {spec.num_trials}: the study's {field} schedule scales with its trials, so a "
                f"run of {spec.num_trials} runs trials 0…{done - 1} under other conditions than this "
                f"run did: {again}"
            )
    return True


def _shortened(text: str, size: int = 80) -> str:
    return text if len(text) <= size else text[: size - 3] + "..."


def different_definition(path, meta: dict, spec) -> StudyError:
    """The refusal to continue ``path``, written by another study definition, naming the fields that differ."""
    theirs, ours = meta.get("definition"), definition(spec)
    differ: list[str] = []
    if isinstance(theirs, dict):

        def value(fields: dict, name: str) -> str:  # an unset field is not recorded (see definition)
            return fields.get(name, "None" if name in _UNSET_UNLESS_GIVEN else "(not recorded)")

        names = [*ours, *(n for n in theirs if n not in ours)]
        differ = [n for n in names if value(theirs, n) != value(ours, n)]
        fields = "; ".join(
            f"{n} {_shortened(str(value(theirs, n)))} there, {_shortened(value(ours, n))} here" for n in differ
        )
    else:
        fields = "it does not record its fields"
    extend = (
        " (its condition changes scale with --trials: a run of another length is another study)"
        if {"num_trials", "schedules"} <= set(differ) <= {"num_trials", "max_trials", "schedules"}
        else ""
    )
    return StudyError(
        f"{path} was written by a different study definition ({fields}){extend}; use another --out, "
        f"or --overwrite to start afresh"
    )


def save_checkpoint(out_dir, spec, ckpt: Checkpoint, backend: str, shard: Shard = Shard()) -> pathlib.Path:
    """Write ``shard``'s checkpoint file atomically (temporary file, fsync, rename); returns its path. ``backend``:
    the simulator's."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    arrays = {f"opt_{i}": np.asarray(a) for i, a in enumerate(ckpt.opt_leaves)}
    arrays.update({f"sim_{i}": np.asarray(a) for i, a in enumerate(ckpt.sim_leaves)})
    arrays["context"] = np.asarray(ckpt.context)
    for name in TrialLog._fields:
        arrays[f"log_{name}"] = np.stack([np.asarray(getattr(lg, name)) for lg in ckpt.logs])
    meta = dict(
        trial=ckpt.trial,
        fingerprint=fingerprint(spec),
        definition=definition(spec),
        backend=backend,
        wall_s=ckpt.wall_s,
        timing=ckpt.timing,
        num_opt=len(ckpt.opt_leaves),
        num_sim=len(ckpt.sim_leaves),
        **shard._asdict(),
    )
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    path = shard_path(out, shard, ckpt.trial)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError as err:  # a full disk: the previous checkpoint is untouched
        tmp.unlink(missing_ok=True)
        kept = f"trials 0…{ckpt.trial - 2} are kept in its checkpoint" if ckpt.trial > 1 else "no trial is kept"
        raise OutputError(
            f"writing the checkpoint of trial {ckpt.trial - 1} in {out} failed ({err.strerror}); "
            f"{kept}: free space, then the same command with --resume continues"
        ) from None
    except BaseException:  # Ctrl-C while writing: the previous checkpoint is the run's, and no half file is left
        tmp.unlink(missing_ok=True)
        raise
    return path


_DAMAGE = (OSError, EOFError, ValueError, KeyError, TypeError, zipfile.BadZipFile, UnicodeDecodeError)


def _corrupt(path, err) -> StudyError:
    # numpy's own messages for a file it cannot parse suggest loading it with pickles: never pass them on
    return StudyError(f"checkpoint {path} is corrupt ({type(err).__name__}); delete it, or use another --out")


def _read_meta(path: pathlib.Path) -> dict:
    """One checkpoint file's metadata.

    Raises:
      StudyError: the file is corrupt (unreadable, truncated, not an archive of ours); the message names it.
    """
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(bytes(z["meta"]).decode())
        if not isinstance(meta, dict) or not isinstance(meta.get("trial"), int):
            raise KeyError("trial")
        return meta
    except _DAMAGE as err:
        raise _corrupt(path, err) from None


def prune_checkpoints(out_dir, shard: Shard, complete_trial: int) -> None:
    """Once every process has written trial ``complete_trial``: delete this process's older files and (rank 0)
    checkpoints of another process count, which a resume no longer needs."""
    for path in checkpoint_files(out_dir):
        m = _SHARD.fullmatch(path.name)
        layout = int(m[2]) if m else 1
        if layout != shard.num_processes:
            if shard.rank == 0:
                path.unlink(missing_ok=True)
        elif m and int(m[1]) == shard.rank and int(m[3]) < complete_trial:
            path.unlink(missing_ok=True)


def _generations(out_dir) -> list[tuple[int, list[pathlib.Path]]]:
    """(trial, files) of every complete checkpoint: the one-process file, and each trial all N processes wrote.

    Raises:
      StudyError: the one-process checkpoint is corrupt.
    """
    found: dict[tuple[int, int], dict[int, pathlib.Path]] = {}
    complete = []
    for path in checkpoint_files(out_dir):
        m = _SHARD.fullmatch(path.name)
        if m is None:
            complete.append((_read_meta(path)["trial"], [path]))
        else:
            found.setdefault((int(m[2]), int(m[3])), {})[int(m[1])] = path
    complete += [(trial, [ranks[r] for r in range(n)]) for (n, trial), ranks in found.items() if len(ranks) == n]
    return sorted(complete, key=lambda g: g[0])


def checkpoint_meta(out_dir) -> dict | None:
    """The metadata (trial, fingerprint, backend, ...) of ``out_dir``'s newest complete checkpoint, None if there is
    none.

    Raises:
      StudyError: the checkpoint is corrupt; the message names it.
    """
    generations = _generations(out_dir)
    return _read_meta(generations[-1][1][0]) if generations else None


def resume_point(out_dir, spec, backend: str) -> int:
    """The trial a resume of ``spec`` on ``backend`` from ``out_dir`` starts at (the trials its checkpoint holds).

    Raises:
      StudyError: no checkpoint, a corrupt one, one of another study definition or of another backend.
    """
    path = pathlib.Path(out_dir) / CHECKPOINT
    meta = checkpoint_meta(out_dir)
    if meta is None:
        raise StudyError(f"--resume: there is no checkpoint in {out_dir}; run without --resume to start afresh")
    if meta.get("fingerprint") != fingerprint(spec) and not extension_of(meta, spec):
        raise different_definition(path, meta, spec)
    if meta.get("backend", backend) != backend:
        raise StudyError(
            f"{path} was written on the {meta['backend']} backend, this run would use {backend}: resume "
            f"with --backend {meta['backend']} (one run, one simulator)"
        )
    return meta["trial"]


def open_run(
    out_dir, spec, backend: str, *, resume: bool = False, overwrite: bool = False, dry_run: bool = False
) -> int:
    """Check a study's output folder before any compute (:func:`claim_folder`; with ``resume``,
    :func:`resume_point`) and return the trial the run starts at (0: afresh). ``dry_run``: check only."""
    start = resume_point(out_dir, spec, backend) if resume else 0
    claim_folder(out_dir, overwrite=overwrite, resume=resume, dry_run=dry_run)
    return start


def load_checkpoint(out_dir, spec, rows: tuple[int, int] | None = None) -> Checkpoint | None:
    """The newest complete checkpoint in ``out_dir`` (None if there is none), its shards merged: the optimizer and
    simulator leaves and the context of instance rows ``rows`` = [first, stop) (default all), every instance's logs.

    Raises:
      StudyError: the checkpoint belongs to a different study definition, or is corrupt.
    """
    generations = _generations(out_dir)
    if not generations:
        return None
    parts = []
    for path in generations[-1][1]:
        meta = _read_meta(path)
        if meta["fingerprint"] != fingerprint(spec) and not extension_of(meta, spec):
            raise different_definition(path, meta, spec)
        try:
            with np.load(path, allow_pickle=False) as z:
                first = meta.get("first_row", 0)
                count = z["context"].shape[0]
                lo, hi = (first, first + count) if rows is None else (max(rows[0], first), min(rows[1], first + count))
                take = slice(lo - first, max(hi - first, lo - first))
                opt = [z[f"opt_{i}"][take] for i in range(meta["num_opt"])]
                sim = [z[f"sim_{i}"][take] for i in range(meta["num_sim"])]
                stacked = [z[f"log_{name}"] for name in TrialLog._fields]
                parts.append((first, meta, opt, sim, z["context"][take], stacked))
        except _DAMAGE as err:
            raise _corrupt(path, err) from None
    parts.sort(key=lambda p: p[0])
    first_meta = parts[0][1]

    def joined(k, axis=0):
        return [np.concatenate(leaves, axis=axis) for leaves in zip(*(p[k] for p in parts), strict=True)]

    stacked = joined(5, axis=1)
    logs = [TrialLog(*(field[t] for field in stacked)) for t in range(first_meta["trial"])]
    return Checkpoint(
        first_meta["trial"],
        joined(2),
        joined(3),
        np.concatenate([p[4] for p in parts]),
        logs,
        first_meta["wall_s"],
        first_meta["timing"],
    )


def process_checkpoint(
    trial: int,
    opt_state: bo.OptimizerState,
    sim_state,
    context: np.ndarray,
    logs: list,
    rows: tuple[int, int],
    wall_s: float,
    timing: dict,
) -> Checkpoint:
    """The checkpoint of one process's instances after ``trial`` trials, what :func:`save_checkpoint` writes.

    Args:
      trial: the trials done.
      opt_state: the optimizer's state of this process's rows of the padded batch (host arrays); of its observation
        buffers the checkpoint keeps the first ``trial`` rows (``optim.bo.first_rows``: at most one observation per
        trial since ``init``, the later rows are ``init``'s).
      sim_state: the simulator's state of the same rows.
      context: (rows, 2) the last context of the same rows.
      logs: a :class:`TrialLog` of the whole padded batch per trial done.
      rows: (first, count): the first of this process's rows in the batch and how many are instances (the rest are
        the padding's copies of the last instance, left out).
      wall_s: compute wall time so far.
      timing: the engine's timing figures so far.
    """
    first, count = rows
    return Checkpoint(
        trial=trial,
        opt_leaves=[leaf[:count] for leaf in jax.tree.leaves(bo.first_rows(opt_state, trial))],
        sim_leaves=[np.asarray(leaf)[:count] for leaf in jax.tree.leaves(sim_state)],
        context=context[:count],
        logs=[TrialLog(*(np.asarray(f)[first : first + count] for f in lg)) for lg in logs],
        wall_s=wall_s,
        timing=dict(timing),
    )


def resume_checkpoint(
    out_dir, spec, fresh: bo.OptimizerState, placement: study_placement.Placement, batch_size: int
) -> Checkpoint | None:
    """The newest checkpoint in ``out_dir`` for this process's rows of the padded batch (None if there is none), the
    inverse of :func:`process_checkpoint`: a padding row takes the saved state of the last instance, which another
    process may hold.

    Args:
      fresh: this process's rows of an optimizer state from ``init`` (host arrays), whose observation buffers past
        the saved rows the resumed state keeps (``optim.bo.full_rows``).
      placement: the batch's placement, whose ``rows`` are this process's.
      batch_size: the study's instances (the padded batch's rows before the padding).

    Returns:
      The checkpoint with ``opt_leaves`` those of the whole optimizer state, ``sim_leaves`` and ``context`` of this
      process's rows, and ``logs`` of the whole padded batch.

    Raises:
      StudyError: the checkpoint belongs to a different study definition, or is corrupt.
    """
    first, stop, last = *placement.rows, batch_size - 1
    ckpt = load_checkpoint(out_dir, spec, (min(first, last), min(stop, last + 1)))
    if ckpt is None:
        return None
    index = np.minimum(np.arange(first, stop), last) - min(first, last)
    saved = jax.tree.unflatten(jax.tree.structure(fresh), [leaf[index] for leaf in ckpt.opt_leaves])
    return ckpt._replace(
        opt_leaves=jax.tree.leaves(bo.full_rows(fresh, saved)),
        sim_leaves=[leaf[index] for leaf in ckpt.sim_leaves],
        context=ckpt.context[index],
        logs=[TrialLog(*(placement.pad(np.asarray(f)[:batch_size]) for f in lg)) for lg in ckpt.logs],
    )


# ----------------------------------------------------------------------------------------------- output paths

_WRITE_PROBE = ".cpgjax-write-check-"  # the name of check_writable's file, before the process id


def _entries(folder: pathlib.Path) -> list[str]:
    """The folder's entries, less the probes of :func:`check_writable` (another process of the same run may be
    checking the folder at this moment)."""
    return sorted(p.name for p in folder.iterdir() if not p.name.startswith(_WRITE_PROBE))


def _check_checkpoint(path: pathlib.Path) -> str | None:
    """A checkpoint's (or shard's) check: its folder's newest complete checkpoint reads back."""
    try:
        checkpoint_meta(path.parent)
    except StudyError as err:
        return str(err)
    return None


# A study's files (and optimize's), beside the trial table (cpgjax.outputs) and best_params.json (cpgjax.trial.tuned).
OUTPUTS = (
    outputs.OutputFile(TABLE, "the study's table (a paper study's: ours beside the paper's)", outputs.check_none),
    outputs.OutputFile(
        CHECKPOINT, "the state after the last finished trial (--resume continues from it)", _check_checkpoint
    ),
    outputs.OutputFile(
        "checkpoint.<rank>of<N>.t<trial>.npz",
        "one process's checkpoint shard (--processes)",
        _check_checkpoint,
        pattern=_SHARD.pattern,
    ),
    outputs.OutputFile(
        RECORDING, "rerun recording: optimization curves and representative rollouts", outputs.check_recording
    ),
    outputs.OutputFile(
        f"{BEST_PARAMS}/<group>.json",
        "the best parameters of each group and what they were tuned for (deploy / walk --params)",
        outputs.check_none,
        pattern=re.escape(BEST_PARAMS),
    ),
)

# Every file name a cpgjax command writes into its output folder, beside the figures (*.png), the checkpoint shards,
# the best gaits' videos (best_<group>.mp4) and the best_params/ folder; --overwrite deletes these and nothing else.
# The robot's files (its per-tick log, trials.rrd, run.json, calibration.json, sim_truth.parquet) and the transfer
# study's evaluations are named here by their names: their writers sit beside this module or above it, where it
# cannot import them (tests/test_outputs.py checks that this list and the catalogue, cpgjax.show.catalogue, name
# the same files).
OUTPUT_FILES = frozenset(
    {
        tuned.FILE_NAME,
        walk.TABLE,
        *(e.name for e in (*outputs.OUTPUTS, *OUTPUTS) if e.pattern is None),
        "trials.rrd",
        "run.json",
        "ticks.arrows",
        "calibration.json",
        "sim_truth.parquet",
        "evaluations.parquet",
    }
)


def _is_output(path: pathlib.Path) -> bool:
    """Whether ``path`` is a file or folder a cpgjax command wrote: a name of :data:`OUTPUT_FILES`, a figure, a
    checkpoint shard or an unfinished checkpoint (``.tmp``), a best gait's video, ``best_params/`` holding only JSON
    files, or a folder holding only such files (an arm of the transfer study)."""
    if path.is_symlink():
        return False
    if path.is_dir():
        inside = list(path.iterdir())
        if path.name == BEST_PARAMS:
            return all(p.suffix == ".json" and p.is_file() for p in inside)
        return bool(inside) and all(_is_output(p) for p in inside)
    name = path.name.removesuffix(".tmp")
    video = name.startswith("best_") and path.suffix == ".mp4"
    return name in OUTPUT_FILES or bool(_SHARD.fullmatch(name)) or path.suffix == ".png" or video


def _remove_outputs(folder: pathlib.Path) -> None:
    """Delete every entry of ``folder`` (each checked by :func:`_is_output`)."""
    for path in folder.iterdir():
        if path.is_dir():
            _remove_outputs(path)
            path.rmdir()
        else:
            path.unlink()


def claim_folder(
    folder, *, overwrite: bool = False, resume: bool = False, resumable: bool = True, dry_run: bool = False
) -> pathlib.Path:
    """Make sure a command may write into ``folder`` before it computes anything, and create it.

    A missing or empty folder is fine; a non-empty one only with ``resume`` (its checkpoint is continued) or
    ``overwrite``: the files a cpgjax command wrote there (:func:`_is_output`) are deleted, so that the run starts
    afresh and no old file is taken for the new run's; anything else in the folder is refused by name, and nothing is
    deleted then. ``resumable``: whether the command has ``--resume`` (the refusal offers it where a checkpoint is).
    ``dry_run``: every check, but nothing deleted or created (a missing folder: its nearest existing parent must be a
    folder this process can write in).

    Raises:
      StudyError: ``folder`` is a file, cannot be created, holds files and neither flag is given, or holds, with
        ``overwrite``, files that no cpgjax command wrote.
    """
    folder = pathlib.Path(folder)
    if folder.exists() and not folder.is_dir():
        raise StudyError(f"{folder} is a file, not a folder: give a folder to write into")
    if folder.is_dir() and not resume:
        entries = _entries(folder)
        if entries and not overwrite:
            hint = " --resume to continue its checkpoint," if resumable and checkpoint_files(folder) else ""
            shown = ", ".join(entries[:3]) + (", ..." if len(entries) > 3 else "")
            raise StudyError(
                f"{folder} is not empty ({shown}): pass{hint} --overwrite to replace its files, or write somewhere else"
            )
        if overwrite:
            foreign = [name for name in entries if not _is_output(folder / name)]
            if foreign:
                shown = ", ".join(foreign[:5]) + (", ..." if len(foreign) > 5 else "")
                raise StudyError(
                    f"{folder}: --overwrite replaces only what cpgjax wrote, and {shown} "
                    f"{'is' if len(foreign) == 1 else 'are'} not cpgjax's: move "
                    f"{'it' if len(foreign) == 1 else 'them'}, or write somewhere else"
                )
            if not dry_run:
                _remove_outputs(folder)
    if dry_run:
        parent = next(p for p in (folder, *folder.absolute().parents) if p.exists())
        if not parent.is_dir():
            raise StudyError(f"cannot create the folder {folder}: {parent} is a file")
        check_writable(parent)
        return folder
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        parent = next(p for p in folder.absolute().parents if p.exists())
        why = (
            f"{parent} takes no new folders ({err.strerror})"
            if err.errno == errno.ENOENT and parent.is_dir()
            else err.strerror
        )
        raise StudyError(f"cannot create the folder {folder}: {why}") from None
    check_writable(folder)
    return folder


def check_writable(folder: pathlib.Path) -> None:
    """Create and delete a file in ``folder``: a read-only folder or file system is found before any compute (a
    permission check would pass for root on a read-only mount).

    Raises:
      StudyError: the file cannot be written; the message names the folder and the reason.
    """
    probe = pathlib.Path(folder) / f"{_WRITE_PROBE}{os.getpid()}"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as err:
        raise StudyError(f"cannot write in {folder}: it takes no new files ({err.strerror})") from None


def claim_file(path, *, overwrite: bool = False) -> pathlib.Path:
    """Make sure a command may write the file ``path`` before it does anything (creating its folder).

    Raises:
      StudyError: ``path`` is a folder, exists and ``overwrite`` is not given, or its folder cannot be created.
    """
    path = pathlib.Path(path)
    if path.is_dir():
        raise StudyError(f"{path} is a folder: give a file name")
    if path.exists() and not overwrite:
        raise StudyError(f"{path} exists: pass --overwrite to replace it, or give another file")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise StudyError(f"cannot create the folder {path.parent}: {err.strerror}") from None
    check_writable(path.parent)
    return path


# ----------------------------------------------------------------------------------------------- trial table


def profile_noise_scale(name: str) -> float:
    """The sensor noise of physics profile ``name`` as a multiple of the robot's (the go1 profile's), NaN where it
    is no multiple of it."""
    noise = np.array(physics_profiles.arrays(physics_profiles.get(name)).noise, np.float64)
    robot = np.array(physics_profiles.arrays(physics_profiles.get(physics_profiles.ROBOT_PROFILE)).noise, np.float64)
    scale = float(np.dot(noise, robot) / np.dot(robot, robot))
    return scale if np.allclose(noise, scale * robot, rtol=1e-6, atol=0.0) else float("nan")


def _resolved(cond, labels: list[dict[str, Any]], n: int) -> tuple[np.ndarray, np.ndarray]:
    """(latency_ticks, noise_scale), each (B, n): the conditions' values with −1 ("the profile's own") replaced by
    the instance's profile's latency and noise scale (:func:`profile_noise_scale`)."""
    profiles = [lab["physics"] for lab in labels]
    own_latency = np.array([physics_profiles.get(p).latency_ticks for p in profiles], np.int64)[:, None]
    own_noise = np.array([profile_noise_scale(p) for p in profiles])[:, None]
    latency = np.asarray(cond.latency_ticks)[:, :n]
    noise = np.asarray(cond.noise_scale, np.float64)[:, :n]
    return np.where(latency >= 0, latency, own_latency).astype(np.int64), np.where(noise >= 0, noise, own_noise)


def trial_columns(result) -> dict[str, np.ndarray]:
    """One row per (instance, trial), instance-major: labels, conditions (those walked, ``result.walked``: a ramp's
    trials at the slopes climbed to), parameters and trial figures. Every float column is float64 (the engine's
    figures are float32, widened exactly), counts int64, flags bool; the latency and the noise scale are resolved to
    the values simulated (docs/outputs.md)."""

    tr, cond = result.trials, result.walked
    n, batch = tr.objective.shape
    inst = np.repeat(np.arange(batch), n)
    trial = np.tile(np.arange(n), batch)

    def per(x):  # (n, B, ...) → (B*n, ...)
        x = np.asarray(x)
        return np.swapaxes(x, 0, 1).reshape((batch * n,) + x.shape[2:])

    cols: dict[str, np.ndarray] = {"instance": inst, "trial": trial}
    gait = ("gait",) if result.spec.gaits is not None else ()  # a study of the trot alone: the table as before gaits
    for label in ("controller", *gait, "seed", "schedule", "data_reuse", "physics"):
        cols[label] = np.array([lab[label] for lab in result.labels])[inst]
    for field in ("friction", "slope_deg", "payload_kg", "target_velocity_mps", "inference", "ramp", "mass_scale"):
        cols[field] = np.asarray(getattr(cond, field))[:, :n].reshape(-1)
    latency, noise = _resolved(cond, result.labels, n)
    cols["latency_ticks"], cols["noise_scale"] = latency.reshape(-1), noise.reshape(-1)
    if result.spec.has_terrain():  # a study on the flat plane alone: the table as before terrains
        for field, values in terrains.ground_fields(map(study_spec.ground, result.labels)).items():
            cols[field] = values[inst]
    if result.spec.foot_friction is not None:  # a study on the profiles' own feet: the table as before the axis
        cols["foot_friction"] = np.array([lab["foot_friction"] for lab in result.labels], np.float64)[inst]
    params = per(tr.params)
    for i, name in enumerate(param_space.PARAM_NAMES):
        cols[name] = params[:, i]
    ctx = per(tr.context)
    cols["c_load_n"], cols["c_slope_rad"] = ctx[:, 0], ctx[:, 1]
    cols["objective"] = per(tr.objective)
    vel = per(tr.velocity_xy_mps)
    cols["velocity_x_mps"], cols["velocity_y_mps"] = vel[:, 0], vel[:, 1]
    cols["cost_of_transport"] = per(tr.cot)
    for name in (
        "beta",
        "roll_std_rad",
        "pitch_std_rad",
        "saturation_fraction",
        "energy_j",
        "distance_m",
        "total_mass_kg",
        "safety_margin",
    ):
        cols[name] = per(getattr(tr, name))
    for name in ("context_changed", "accepted", "fell", "failed", "safe_fallback"):
        cols[name] = per(getattr(tr, name)) > 0
    return {
        k: v.astype(np.float64)
        if np.issubdtype(v.dtype, np.floating)
        else v.astype(np.int64)
        if np.issubdtype(v.dtype, np.integer)
        else v
        for k, v in cols.items()
    }


def write_trials(result, path) -> pathlib.Path:
    """``trials.parquet`` (see :func:`trial_columns`)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = pathlib.Path(path)
    columns = trial_columns(result)
    # a noise scale that is no multiple of the robot's is null (docs/outputs.md), not NaN
    columns["noise_scale"] = pa.array(columns["noise_scale"], mask=np.isnan(columns["noise_scale"]))
    pq.write_table(pa.table(columns), path)
    return path


def read_trials(path) -> dict[str, np.ndarray]:
    """``trials.parquet`` (:func:`write_trials`) back as one (trials, instances) array per column: element [t, b] is
    instance b's trial t."""
    import pyarrow.parquet as pq

    rows = {k: np.asarray(v) for k, v in pq.read_table(path).to_pydict().items()}
    n_trial, batch = rows["trial"].max() + 1, rows["instance"].max() + 1
    grids = {}
    for name, values in rows.items():
        grids[name] = np.empty((n_trial, batch), values.dtype)
        grids[name][rows["trial"], rows["instance"]] = values
    return grids


@contextlib.contextmanager
def writing(out_dir, what: str):
    """Turn any failure while writing ``what`` into :class:`OutputError`: which file, why, the files already in
    ``out_dir`` (the checkpoint holds every trial) and that ``--resume`` writes the outputs again."""
    try:
        yield
    except Exception as err:  # an output's failure, whatever its kind, must not hide the results already kept
        out = pathlib.Path(out_dir)
        kept = ", ".join(_entries(out)) if out.is_dir() else "nothing"
        raise OutputError(
            f"writing {what} in {out} failed ({type(err).__name__}: {err}); kept: {kept}. Every trial "
            f"is in its checkpoint: the same command with --resume writes the outputs again"
        ) from err


# --------------------------------------------------------------------------------------- a run's folder and plan


def output_folder(name: str, out=None) -> pathlib.Path:
    """A study's output folder: ``out``, by default ``results/<name>``."""
    return pathlib.Path(out or pathlib.Path("results") / name)


def run_plan(spec, out_dir, backend: str, start: int) -> str:
    """One line on what a study run would compute (``--dry-run``): instances, trials, env-steps, where it writes, and
    its wall time at this machine's measured rate (:func:`rate.estimate`)."""
    batch = len(study_spec.instances(spec))
    steps = spec.trial.transition_steps + spec.trial.steady_steps
    remaining = batch * (spec.num_trials - start) * steps
    axes = ", ".join(
        f"{len(getattr(spec, a))} {a}"
        for a in (
            "controllers",
            "seeds",
            "friction",
            "slope_deg",
            "payload_kg",
            "target_velocity_mps",
            "schedules",
            "data_reuse",
            "physics",
        )
        if len(getattr(spec, a)) > 1
    )
    where = f"resuming {out_dir} at trial {start}" if start else f"writing {out_dir}/"
    return (
        f"{spec.name}: {batch} instances ({axes or 'one'}) × {spec.num_trials} trials of {steps * TICK_S:g} s"
        f"{', safe' if spec.safe else ''}: {remaining:,} env-steps ({remaining * TICK_S / 3600:.2f} robot-hours) "
        f"on the {backend} backend, {where}; {rate.estimate(backend, remaining)}"
    )


def resume_notice(out: pathlib.Path, start: int, num_trials: int) -> str:
    return f"resuming {out} at trial {start} (trials are numbered from 0; {start} of {num_trials} are done)"


# ----------------------------------------------------------------------------------------------- metadata


def run_figures(result) -> dict[str, float]:
    """Wall time, env-steps/s and real-time factor (simulated robot-seconds per wall-second) of a study."""
    spec = result.spec
    steps_per_trial = spec.trial.transition_steps + spec.trial.steady_steps
    env_steps = len(result.labels) * result.trials.objective.shape[0] * steps_per_trial
    robot_s = env_steps * TICK_S
    wall = max(result.wall_s, 1e-9)
    return dict(
        wall_s=round(result.wall_s, 2),
        env_steps=env_steps,
        robot_s=round(robot_s, 1),
        env_steps_per_s=round(env_steps / wall, 1),
        real_time_factor=round(robot_s / wall, 2),
        simulation_s=round(result.timing.simulation_s, 2),
        optimizer_s=round(result.timing.optimizer_s, 2),
        propose_s=round(result.timing.propose_s, 2),
        observe_s=round(result.timing.observe_s, 2),
        transfer_s=round(result.timing.transfer_s, 2),
        exchange_s=round(result.timing.exchange_s, 2),
        checkpoint_s=round(result.timing.checkpoint_s, 2),
    )


def write_metadata(
    result, path, extra: dict | None = None, command: str | None = None, written_by: str = "study"
) -> dict:
    """``metadata.json``: the study, the cpgjax command that wrote the folder (``written_by``: ``study`` or
    ``optimize``), how it was run (``command``: the exact command line) and its run figures (``compiled_programs``:
    how many of the process's programs were loaded from the cache of compiled programs and how many compiled, which
    the first trial's time depends on; null without the cache)."""
    figures = run_figures(result)
    meta = dict(
        study=result.spec.name,
        written_by=written_by,
        command=command,
        cpgjax_version=cpgjax.__version__,
        git_commit=provenance.git_commit(),
        instances=len(result.labels),
        trials=int(result.trials.objective.shape[0]),
        backend=result.backend,
        sharded_over=result.devices,
        spec=repr(result.spec),
        optimizer=dataclasses.asdict(result.spec.optimizer_config()),
        **figures,
        environment=provenance.environment(),
        compiled_programs=compile_cache.counts(),
        **(extra or {}),
    )
    pathlib.Path(path).write_text(json.dumps(meta, indent=2, default=str))
    if result.wall_s > 0.0:
        rate.record(result.backend, figures, result.spec.name, len(result.labels))
    return meta


# ----------------------------------------------------------------------------------------------- rerun


def instance_path(labels: list[dict[str, Any]], b: int) -> str:
    """Instance ``b``'s entity path below each recorded series: every label that differs between the study's
    instances as ``label=value`` (controller and seed always), then ``i<b>``; so the friction 0.3 and 0.9 curves, or
    the runs with and without data reuse, are told apart in the viewer."""
    import rerun as rr

    keys = [k for k in labels[0] if k in ("controller", "seed") or len({str(lab[k]) for lab in labels}) > 1]
    return "/".join(rr.escape_entity_path_part(f"{k}={labels[b][k]}") for k in keys) + f"/i{b}"


def write_recording(result, path, rollouts: list | None = None) -> pathlib.Path:
    """A rerun ``.rrd``: per-instance trial curves on timeline ``trial``, and each rollout (``study.scene.Rollout``)
    full body on timelines ``step`` and ``sim_time`` (:func:`cpgjax.study.scene.log_rollout`)."""
    import rerun as rr

    path = pathlib.Path(path)
    rec = rr.RecordingStream(f"cpgjax_{result.spec.name}")
    rec.save(str(path))
    rr.log("/", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True, recording=rec)
    tr = result.trials
    n = tr.objective.shape[0]
    trial_index = rr.TimeColumn("trial", sequence=np.arange(n))
    series = dict(
        objective=tr.objective,
        velocity_x_mps=tr.velocity_xy_mps[..., 0],
        cost_of_transport=tr.cot,
        c_load_n=tr.context[..., 0],
        c_slope_rad=tr.context[..., 1],
        beta=tr.beta,
    )
    for b in range(len(result.labels)):
        name = instance_path(result.labels, b)
        for key, values in series.items():
            rr.send_columns(
                f"optimization/{key}/{name}",
                indexes=[trial_index],
                columns=rr.Scalars.columns(scalars=np.asarray(values[:, b], np.float64)),
                recording=rec,
            )
    bases = [study_scene.log_rollout(rec, rollout) for rollout in rollouts or ()]
    rec.send_blueprint(study_scene.blueprint(bases))
    rec.flush()
    rec.disconnect()
    return path
