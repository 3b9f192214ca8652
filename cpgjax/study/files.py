"""A study's files: the per-trial checkpoint, the columnar trial table, the rerun recording and the run metadata.

* ``checkpoint.npz`` — the whole engine state after trial t (optimizer and simulator leaves, last context, every
  trial's log, wall time), written to a temporary file and renamed (atomic: a kill leaves the previous one). It
  carries the study's fingerprint; resuming a different study from it is refused. With N processes each writes the
  rows of its own instances, ``checkpoint.<rank>of<N>.t<trial>.npz``, and keeps its previous trial's file until
  every process has written the next one; reading merges the newest trial all N wrote (docs/scaling.md).
* ``trials.parquet`` — one row per (instance, trial): instance labels, conditions, the 8 parameters, context, J,
  velocity, CoT, falls. ``pandas.read_parquet(path)`` or ``polars.read_parquet(path)``.
* ``recording.rrd`` — rerun: optimization progress (J, velocity, CoT, context per trial and instance) and
  representative rollouts (trunk pose and feet per step, foot forces, CPG phases and amplitudes).
* ``metadata.json`` — versions, devices, backend, wall time, env-steps/s and real-time factor.
"""

from __future__ import annotations

import json
import os
import pathlib
import platform
import re
import sys
from typing import Any, NamedTuple

import numpy as np

from cpgjax.go1 import model as go1_model
from cpgjax.study.spec import StudyError
from cpgjax.trial import params as param_space

CHECKPOINT = "checkpoint.npz"
_SHARD = re.compile(r"checkpoint\.(\d+)of(\d+)\.t(\d+)\.npz")


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


def fingerprint(spec) -> str:
    """A string that changes whenever the study's definition does (its full repr)."""
    return repr(spec)


def save_checkpoint(out_dir, spec, ckpt: Checkpoint, shard: Shard = Shard()) -> pathlib.Path:
    """Write ``shard``'s checkpoint file atomically (temporary file, fsync, rename); returns its path."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    arrays = {f"opt_{i}": np.asarray(a) for i, a in enumerate(ckpt.opt_leaves)}
    arrays.update({f"sim_{i}": np.asarray(a) for i, a in enumerate(ckpt.sim_leaves)})
    arrays["context"] = np.asarray(ckpt.context)
    for name in TrialLog._fields:
        arrays[f"log_{name}"] = np.stack([np.asarray(getattr(lg, name)) for lg in ckpt.logs])
    meta = dict(trial=ckpt.trial, fingerprint=fingerprint(spec), wall_s=ckpt.wall_s, timing=ckpt.timing,
                num_opt=len(ckpt.opt_leaves), num_sim=len(ckpt.sim_leaves), **shard._asdict())
    arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    path = shard_path(out, shard, ckpt.trial)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    return path


def prune_checkpoints(out_dir, shard: Shard, complete_trial: int) -> None:
    """Once every process has written trial ``complete_trial``: delete this process's older files and (rank 0)
    checkpoints of another process count, which a resume no longer needs."""
    for path in checkpoint_files(out_dir):
        m = _SHARD.fullmatch(path.name)
        layout = (int(m[2]) if m else 1)
        if layout != shard.num_processes:
            if shard.rank == 0:
                path.unlink(missing_ok=True)
        elif m and int(m[1]) == shard.rank and int(m[3]) < complete_trial:
            path.unlink(missing_ok=True)


def _generations(out_dir) -> list[tuple[int, list[pathlib.Path]]]:
    """(trial, files) of every complete checkpoint: the one-process file, and each trial all N processes wrote."""
    found: dict[tuple[int, int], dict[int, pathlib.Path]] = {}
    complete = []
    for path in checkpoint_files(out_dir):
        m = _SHARD.fullmatch(path.name)
        if m is None:
            with np.load(path) as z:
                complete.append((json.loads(bytes(z["meta"]).decode())["trial"], [path]))
        else:
            found.setdefault((int(m[2]), int(m[3])), {})[int(m[1])] = path
    complete += [(trial, [ranks[r] for r in range(n)]) for (n, trial), ranks in found.items() if len(ranks) == n]
    return sorted(complete, key=lambda g: g[0])


def load_checkpoint(out_dir, spec, rows: tuple[int, int] | None = None) -> Checkpoint | None:
    """The newest complete checkpoint in ``out_dir`` (None if there is none), its shards merged: the optimizer and
    simulator leaves and the context of instance rows ``rows`` = [first, stop) (default all), every instance's logs.

    Raises:
      StudyError: the checkpoint belongs to a different study definition.
    """
    generations = _generations(out_dir)
    if not generations:
        return None
    parts = []
    for path in generations[-1][1]:
        with np.load(path) as z:
            meta = json.loads(bytes(z["meta"]).decode())
            if meta["fingerprint"] != fingerprint(spec):
                raise StudyError(f"{path} was written by a different study definition; use another --out or delete "
                                 f"it (checkpoint: {meta['fingerprint'][:200]}...)")
            first = meta.get("first_row", 0)
            count = z["context"].shape[0]
            lo, hi = (first, first + count) if rows is None else (max(rows[0], first), min(rows[1], first + count))
            take = slice(lo - first, max(hi - first, lo - first))
            opt = [z[f"opt_{i}"][take] for i in range(meta["num_opt"])]
            sim = [z[f"sim_{i}"][take] for i in range(meta["num_sim"])]
            stacked = [z[f"log_{name}"] for name in TrialLog._fields]
            parts.append((first, meta, opt, sim, z["context"][take], stacked))
    parts.sort(key=lambda p: p[0])
    first_meta = parts[0][1]

    def joined(k, axis=0):
        return [np.concatenate(leaves, axis=axis) for leaves in zip(*(p[k] for p in parts))]
    stacked = joined(5, axis=1)
    logs = [TrialLog(*(field[t] for field in stacked)) for t in range(first_meta["trial"])]
    return Checkpoint(first_meta["trial"], joined(2), joined(3), np.concatenate([p[4] for p in parts]), logs,
                      first_meta["wall_s"], first_meta["timing"])


# ----------------------------------------------------------------------------------------------- trial table

def trial_columns(result) -> dict[str, np.ndarray]:
    """One row per (instance, trial), instance-major: labels, conditions, parameters and trial figures."""

    tr, cond = result.trials, result.conditions
    n, batch = tr.objective.shape
    inst = np.repeat(np.arange(batch), n)
    trial = np.tile(np.arange(n), batch)

    def per(x):  # (n, B, ...) → (B*n, ...)
        x = np.asarray(x)
        return np.swapaxes(x, 0, 1).reshape((batch * n,) + x.shape[2:])

    cols: dict[str, np.ndarray] = {"instance": inst, "trial": trial}
    for label in ("controller", "seed", "schedule", "data_reuse", "physics"):
        cols[label] = np.array([lab[label] for lab in result.labels])[inst]
    for field in ("friction", "slope_deg", "payload_kg", "target_velocity_mps", "inference", "mass_scale",
                  "latency_ticks", "noise_scale"):
        cols[field] = np.asarray(getattr(cond, field))[:, :n].reshape(-1)
    params = per(tr.params)
    for i, name in enumerate(param_space.PARAM_NAMES):
        cols[name] = params[:, i]
    ctx = per(tr.context)
    cols["c_load_n"], cols["c_slope_rad"] = ctx[:, 0], ctx[:, 1]
    cols["objective"] = per(tr.objective)
    vel = per(tr.velocity_xy_mps)
    cols["velocity_x_mps"], cols["velocity_y_mps"] = vel[:, 0], vel[:, 1]
    for name in ("cot", "beta", "context_changed", "accepted", "roll_std_rad", "pitch_std_rad",
                 "saturation_fraction", "energy_j", "distance_m", "total_mass_kg", "fell", "failed"):
        cols[name] = per(getattr(tr, name))
    return cols


def write_trials(result, path) -> pathlib.Path:
    """``trials.parquet`` (see :func:`trial_columns`)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    path = pathlib.Path(path)
    pq.write_table(pa.table(trial_columns(result)), path)
    return path


# ----------------------------------------------------------------------------------------------- metadata

def cpu_model() -> str:
    """The CPU's model name (what lscpu reports), or the platform's processor string where it cannot be read."""
    try:
        with open("/proc/cpuinfo") as f:
            return next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor() or "unknown CPU"


def machine() -> str:
    """'<CPU model>, <n> CPUs': how benchmarks and study metadata name the machine."""
    return f"{cpu_model()}, {os.cpu_count()} CPUs"


def environment() -> dict[str, Any]:
    import jax
    import mujoco

    cpu = cpu_model()
    return dict(python=sys.version.split()[0], jax=jax.__version__, mujoco=mujoco.__version__,
                numpy=np.__version__, platform=platform.platform(), cpu=cpu, cpu_count=os.cpu_count(),
                load_avg=os.getloadavg() if hasattr(os, "getloadavg") else None,
                jax_backend=jax.default_backend(), devices=[str(d) for d in jax.devices()],
                xla_flags=os.environ.get("XLA_FLAGS", ""))


def run_figures(result) -> dict[str, float]:
    """Wall time, env-steps/s and real-time factor (simulated robot-seconds per wall-second) of a study."""
    spec = result.spec
    steps_per_trial = spec.trial.transition_steps + spec.trial.steady_steps
    env_steps = len(result.labels) * result.trials.objective.shape[0] * steps_per_trial
    robot_s = env_steps * 0.001
    wall = max(result.wall_s, 1e-9)
    return dict(wall_s=round(result.wall_s, 2), env_steps=env_steps, robot_s=round(robot_s, 1),
                env_steps_per_s=round(env_steps / wall, 1), real_time_factor=round(robot_s / wall, 2),
                simulation_s=round(result.timing.simulation_s, 2), optimizer_s=round(result.timing.optimizer_s, 2),
                propose_s=round(result.timing.propose_s, 2), observe_s=round(result.timing.observe_s, 2),
                transfer_s=round(result.timing.transfer_s, 2), exchange_s=round(result.timing.exchange_s, 2),
                checkpoint_s=round(result.timing.checkpoint_s, 2))


def write_metadata(result, path, extra: dict | None = None) -> dict:
    meta = dict(study=result.spec.name, instances=len(result.labels), trials=int(result.trials.objective.shape[0]),
                backend=result.backend, sharded_over=result.devices, spec=repr(result.spec),
                **run_figures(result), environment=environment(), **(extra or {}))
    pathlib.Path(path).write_text(json.dumps(meta, indent=2, default=str))
    return meta


# ----------------------------------------------------------------------------------------------- rerun

def write_recording(result, path, rollouts: dict[str, Any] | None = None) -> pathlib.Path:
    """A rerun ``.rrd``: per-instance trial curves on timeline ``trial``, and each rollout (a ``protocol.StepLog``
    of one instance, arrays (T, ...)) on timeline ``step`` (1 ms ticks)."""
    import rerun as rr


    path = pathlib.Path(path)
    rec = rr.RecordingStream(f"cpgjax_{result.spec.name}")
    rec.save(str(path))
    tr = result.trials
    n = tr.objective.shape[0]
    trial_index = rr.TimeColumn("trial", sequence=np.arange(n))
    series = dict(objective=tr.objective, velocity_x_mps=tr.velocity_xy_mps[..., 0], cot=tr.cot,
                  c_load_n=tr.context[..., 0], c_slope_rad=tr.context[..., 1], beta=tr.beta)
    for b, lab in enumerate(result.labels):
        name = "/".join(str(lab[k]) for k in ("controller", "seed")) + f"/i{b}"
        for key, values in series.items():
            rr.send_columns(f"optimization/{key}/{name}", indexes=[trial_index],
                            columns=rr.Scalars.columns(scalars=np.asarray(values[:, b], np.float64)),
                            recording=rec)
    ids = go1_model.indices()
    for label, step_log in (rollouts or {}).items():
        qpos = np.asarray(step_log.qpos, np.float64)
        steps = rr.TimeColumn("step", sequence=np.arange(qpos.shape[0]))
        base = f"rollout/{label}"
        r = ids.root_qpos
        quat_xyzw = qpos[:, [r + 4, r + 5, r + 6, r + 3]]
        rr.log(f"{base}/world/trunk", rr.Boxes3D(half_sizes=[[0.19, 0.05, 0.06]]), static=True, recording=rec)
        rr.send_columns(f"{base}/world/trunk", indexes=[steps],
                        columns=rr.Transform3D.columns(translation=qpos[:, r:r + 3], quaternion=quat_xyzw),
                        recording=rec)
        feet = np.asarray(step_log.foot_pos_m, np.float64)  # (T, 4, 3)
        rr.send_columns(f"{base}/world/feet", indexes=[steps],
                        columns=rr.Points3D.columns(positions=feet.reshape(-1, 3)).partition([4] * feet.shape[0]),
                        recording=rec)
        for k, leg in enumerate(("FR", "FL", "RR", "RL")):
            for key, values in (("foot_force_n", step_log.foot_force_n), ("phase_rad", step_log.phase_rad),
                                ("amplitude", step_log.amplitude)):
                rr.send_columns(f"{base}/{key}/{leg}", indexes=[steps],
                                columns=rr.Scalars.columns(scalars=np.asarray(values[:, k], np.float64)),
                                recording=rec)
        for k, axis in enumerate(("roll", "pitch", "yaw")):
            rr.send_columns(f"{base}/attitude_rad/{axis}", indexes=[steps],
                            columns=rr.Scalars.columns(scalars=np.asarray(step_log.rpy_rad[:, k], np.float64)),
                            recording=rec)
    rec.flush()
    rec.disconnect()
    return path
