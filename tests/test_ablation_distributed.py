"""Multi-process studies on 127.0.0.1 (docs/scaling.md): 2 processes × 1 CPU device against the 1-process run, a
killed process, the checkpoint it leaves behind, the exchange's timeout, shard files, and ``--processes``'s options.

The studies are test_ablation's tiny one (4 instances, 5 short trials, native backend); each process of a 2-process
run simulates 2 of the instances.
"""

import io
import os
import pathlib
import subprocess
import sys
import time

import numpy as np
import pytest

from cpgjax import cli
from cpgjax.studies import launch
from cpgjax.study import files as study_io
from cpgjax.study import spec as study_spec
from tests.test_ablation import SPEC_SOURCE, TRIALS, tiny_spec

ROOT = pathlib.Path(__file__).resolve().parents[1]
ENV = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(ROOT))
# Process `kill_rank` SIGKILLs itself once its checkpoint of trial `kill_after` is on disk (after the exchange of
# that trial, so every process has trial `kill_after` − 1 on disk: a mid-study kill).
CHILD = (
    SPEC_SOURCE
    + """
import os, pathlib, signal, sys, threading, time, jax
out, resume, kill_rank, kill_after = sys.argv[1], sys.argv[2] == "resume", int(sys.argv[3]), int(sys.argv[4])
study_placement.initialize_distributed()
assert jax.process_count() == 2 and len(jax.local_devices()) == 1
def kill_when_written():
    mine = pathlib.Path(out) / f"checkpoint.{kill_rank}of2.t{kill_after:06d}.npz"
    while not mine.exists():
        time.sleep(0.01)
    os.kill(os.getpid(), signal.SIGKILL)
if jax.process_index() == kill_rank:
    threading.Thread(target=kill_when_written, daemon=True).start()
result = ablation.Engine(spec, backend="native").run(out, resume=resume)
print("rows", result.rows, "timing", dict(result.timing._asdict()))
"""
)
# The 1-process reference on as many devices (2 CPU devices): the optimizer's arrays are then split the same way.
ONE_PROCESS = (
    SPEC_SOURCE
    + """
import sys, jax
assert jax.process_count() == 1 and len(jax.devices()) == 2
ablation.Engine(spec, backend="native").run(sys.argv[1])
"""
)


# The optimizer's compiled programs on 2 CPU devices: the collectives XLA put in them (none, each device computes its
# own instances' rows).
COLLECTIVES = (
    SPEC_SOURCE
    + """
import re, jax, numpy as np
assert len(jax.devices()) == 2
engine = ablation.Engine(spec, backend="native")
put = engine.placement.put
state = engine.initial_opt_state()
context = engine.placement.put_local(engine.initial_context())
keys = engine.sharded.keys(put(engine.batch.seeds.astype(np.uint32)), 0)
x = put(np.full((engine.placement.padded_size, 8), 0.5, np.float32))
ones = put(np.ones(engine.placement.padded_size, np.float32))
programs = {"propose": engine.sharded.propose.lower(state, context, keys),
            "observe": engine.sharded.observe.lower(state, x, context, ones, ones),
            "beta": engine.sharded.beta.lower(state, context)}
pattern = r"(all-gather|all-reduce|all-to-all|collective-permute|reduce-scatter)"
for name, lowered in programs.items():
    found = re.findall(pattern, lowered.compile().as_text())
    print(name, len(found), sorted(set(found)))
"""
)


def test_the_optimizer_computes_each_devices_own_instances_without_collectives():
    """Per-instance work needs no other device's data (docs/scaling.md): on 2 CPU devices the optimizer's programs
    hold no collective. Left to jit's partitioner, observe gathered the whole batch 10 times (each process then
    computed, and exchanged, every instance's optimizer)."""
    run = subprocess.run(
        [sys.executable, "-c", COLLECTIVES],
        capture_output=True,
        text=True,
        timeout=600,
        env=dict(ENV, XLA_FLAGS="--xla_force_host_platform_device_count=2"),
    )
    assert run.returncode == 0, run.stderr[-3000:]
    counts = dict(line.split()[:2] for line in run.stdout.splitlines())
    assert counts == {"propose": "0", "observe": "0", "beta": "0"}, run.stdout


def _launch(out, *, resume=False, kill_rank=-1, kill_after=0):
    buffer = io.StringIO()
    t0 = time.monotonic()
    outcome = launch.run(
        [sys.executable, "-c", CHILD, str(out), "resume" if resume else "fresh", str(kill_rank), str(kill_after)],
        2,
        env=ENV,
        out=buffer,
    )
    return outcome, buffer.getvalue(), time.monotonic() - t0


@pytest.fixture(scope="module")
def two_processes(tmp_path_factory):
    out = tmp_path_factory.mktemp("two") / "study"
    outcome, text, _ = _launch(out)
    assert outcome.returncode == 0, text[-3000:]
    return out, text


def test_two_processes_equal_one_process(two_processes, tmp_path):
    """2 processes × 1 CPU device against 1 process × 2 CPU devices: bit for bit (tolerance zero).

    Each process simulates 2 of the 4 instances where the single process simulates all 4 in one batch; the native
    backend's physics is per instance and its vectorized controller tick gives the same bits for 2 or 4 instances
    (measured here). The optimizer's shards are the same (2 instances per device) in both. Against 1 process on
    1 device the optimizer runs 4 instances per device, and XLA's other vectorization changes the UCB argmax in the
    float32 rounding (the cpgjax.ablation docstring): that case is test_ablation's sharded-vs-unsharded test, with
    its tolerance."""
    out, text = two_processes
    assert "[rank 0] rows (0, 2)" in text and "[rank 1] rows (2, 4)" in text, text[-2000:]
    ckpt = study_io.load_checkpoint(out, tiny_spec())
    assert ckpt.trial == TRIALS
    # one shard per process, only the last trial's kept once every process had written it
    assert sorted(p.name for p in study_io.checkpoint_files(out)) == [
        f"checkpoint.{r}of2.t{t:06d}.npz" for r in (0, 1) for t in (TRIALS - 1, TRIALS)
    ]
    one = subprocess.run(
        [sys.executable, "-c", ONE_PROCESS, str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=600,
        env=dict(ENV, XLA_FLAGS="--xla_force_host_platform_device_count=2"),
    )
    assert one.returncode == 0, one.stderr[-3000:]
    reference = study_io.load_checkpoint(tmp_path, tiny_spec())
    assert len(reference.logs) == len(ckpt.logs) == TRIALS
    for a, b in zip(ckpt.logs, reference.logs, strict=True):
        for name in study_io.TrialLog._fields:
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), name)
    for a, b in zip(ckpt.opt_leaves + ckpt.sim_leaves, reference.opt_leaves + reference.sim_leaves, strict=True):
        np.testing.assert_array_equal(a, b)


def test_killed_process_stops_the_run_and_its_checkpoint_resumes(tmp_path, two_processes):
    out = tmp_path / "study"
    outcome, text, wall_s = _launch(out, kill_rank=1, kill_after=3)
    assert outcome.returncode != 0 and "process rank 1 of 2 was killed by signal SIGKILL" in outcome.message, (
        outcome,
        text[-3000:],
    )
    assert wall_s < 200, f"the run took {wall_s:.0f} s to stop"
    left = study_io.load_checkpoint(out, tiny_spec())
    assert 2 <= left.trial < TRIALS, left.trial
    outcome, text, _ = _launch(out, resume=True)
    assert outcome.returncode == 0, text[-3000:]
    resumed, uninterrupted = (
        study_io.load_checkpoint(out, tiny_spec()),
        study_io.load_checkpoint(two_processes[0], tiny_spec()),
    )
    for a, b in zip(resumed.logs, uninterrupted.logs, strict=True):
        for name in study_io.TrialLog._fields:
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), name)
    for a, b in zip(
        resumed.opt_leaves + resumed.sim_leaves, uninterrupted.opt_leaves + uninterrupted.sim_leaves, strict=True
    ):
        np.testing.assert_array_equal(a, b)


HUNG = """
import sys, time, jax
from cpgjax.study import placement as study_placement
study_placement.initialize_distributed()
if jax.process_index() == 1:
    time.sleep(60)  # alive and connected, never answers
try:
    study_placement.exchange({"x": jax.numpy.zeros(3)}, timeout_s=3.0)
except study_placement.ProcessLost as err:
    print("lost:", err)
    sys.stdout.flush()
    import os; os._exit(3)
"""


def test_an_unanswered_exchange_times_out_naming_the_rank():
    buffer = io.StringIO()
    t0 = time.monotonic()
    outcome = launch.run([sys.executable, "-c", HUNG], 2, env=ENV, out=buffer)
    text = buffer.getvalue()
    assert "[rank 0] lost: process 0: no trial data from process 1 of 2 within 3 s" in text, text[-2000:]
    assert outcome.message.startswith("process rank 0 of 2 exited with code 3; stopped the other processes")
    assert time.monotonic() - t0 < 45  # rank 1 was stopped, not waited for


def _shard(out, spec, rank, n, first, trial, rows):
    """A fake checkpoint shard whose every number is its instance's row (first … first + rows − 1)."""
    values = np.arange(first, first + rows, dtype=np.float64)
    log = study_io.TrialLog(*(values for _ in study_io.TrialLog._fields))
    study_io.save_checkpoint(
        out,
        spec,
        study_io.Checkpoint(trial, [values[:, None] * 10], [values], values[:, None], [log] * trial, 1.0 * rank, {}),
        "native",
        study_io.Shard(rank, n, first),
    )


def test_shards_merge_on_read_from_the_newest_complete_trial(tmp_path):
    spec = tiny_spec()
    for rank in (0, 1):
        _shard(tmp_path, spec, rank, 2, 2 * rank, 3, 2)
    _shard(tmp_path, spec, 0, 2, 0, 4, 2)  # rank 1 died before writing trial 4
    ckpt = study_io.load_checkpoint(tmp_path, spec)
    assert ckpt.trial == 3 and ckpt.wall_s == 0.0  # rank 0's wall time
    np.testing.assert_array_equal(ckpt.context[:, 0], [0, 1, 2, 3])
    np.testing.assert_array_equal(ckpt.logs[2].objective, [0, 1, 2, 3])
    part = study_io.load_checkpoint(tmp_path, spec, rows=(1, 3))  # a process that holds rows 1 and 2
    np.testing.assert_array_equal(part.opt_leaves[0][:, 0], [10, 20])
    np.testing.assert_array_equal(part.logs[0].objective, [0, 1, 2, 3])  # every instance's logs
    # a 1-process resume from trial 3: once its own file holds trial 4, the 2-process shards go
    _shard(tmp_path, spec, 0, 1, 0, 4, 4)
    assert study_io.load_checkpoint(tmp_path, spec).trial == 4
    study_io.prune_checkpoints(tmp_path, study_io.Shard(0, 1, 0), 4)
    assert [p.name for p in study_io.checkpoint_files(tmp_path)] == [study_io.CHECKPOINT]
    # 2 processes: once both have written trial 5, each deletes its files before it
    for rank in (0, 1):
        _shard(tmp_path, spec, rank, 2, 2 * rank, 5, 2)
        _shard(tmp_path, spec, rank, 2, 2 * rank, 6, 2)
    study_io.prune_checkpoints(tmp_path, study_io.Shard(1, 2, 2), 5)
    assert sorted(p.name for p in study_io.checkpoint_files(tmp_path)) == [
        "checkpoint.0of2.t000005.npz",
        "checkpoint.0of2.t000006.npz",
        "checkpoint.1of2.t000005.npz",
        "checkpoint.1of2.t000006.npz",
        study_io.CHECKPOINT,
    ]
    study_io.prune_checkpoints(tmp_path, study_io.Shard(0, 2, 0), 6)  # rank 0 also deletes the 1-process file
    assert sorted(p.name for p in study_io.checkpoint_files(tmp_path)) == [
        "checkpoint.0of2.t000006.npz",
        "checkpoint.1of2.t000005.npz",
        "checkpoint.1of2.t000006.npz",
    ]
    assert study_io.load_checkpoint(tmp_path, spec).trial == 6


def test_launched_command_line_drops_processes_and_keeps_the_rest():
    keep = ["study", "friction", "--seeds", "2", "--out", "x"]
    for extra in (["--processes", "3"], ["--processes=3"], ["--proc", "3"]):
        assert cli._without_processes(keep[:2] + extra + keep[2:]) == keep


def test_mjx_refuses_the_cpu_layout_that_deadlocks(monkeypatch):
    """More than 64 instances on each of as many CPU devices as cores: jaxlib's batched Cholesky deadlocks (gdb on
    benchmarks/cpu_devices_hang.py); refused with the cause and the workarounds, before any compute."""
    import jax

    from cpgjax.sim import backends, native_physics

    cpu = jax.devices("cpu")[0]
    monkeypatch.setattr(native_physics, "available_cores", lambda: 2)
    with pytest.raises(ValueError, match="128 instances on each of 2 CPU devices .2 cores. never finishes") as err:
        backends.check_mjx_layout(128, [cpu, cpu])
    assert "--processes 2" in str(err.value) and "native backend" in str(err.value)
    backends.check_mjx_layout(64, [cpu, cpu])  # measured to complete
    backends.check_mjx_layout(128, [cpu])  # one device: a free thread runs the pieces
    monkeypatch.setattr(native_physics, "available_cores", lambda: 4)
    backends.check_mjx_layout(128, [cpu, cpu])


def test_a_corrupt_shard_is_named_and_the_backend_is_kept(tmp_path):
    spec = tiny_spec()
    for rank in (0, 1):
        _shard(tmp_path, spec, rank, 2, 2 * rank, 3, 2)
    assert study_io.checkpoint_meta(tmp_path)["backend"] == "native"
    with pytest.raises(study_spec.StudyError, match="on the native backend"):
        study_io.resume_point(tmp_path, spec, "mjx")
    damaged = study_io.shard_path(tmp_path, study_io.Shard(1, 2, 2), 3)
    damaged.write_bytes(b"not a checkpoint")
    with pytest.raises(study_spec.StudyError, match=f"checkpoint {damaged} is corrupt") as err:
        study_io.load_checkpoint(tmp_path, spec)
    assert "pickle" not in str(err.value).lower()
