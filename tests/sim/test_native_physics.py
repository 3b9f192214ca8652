"""The native backend's steppings (``cpgjax.sim.native_physics.STEPPINGS``) against each other and the reference.

- ``batch`` (``mujoco.batch`` from Python, one jitted call per tick) against the reference, one ``mujoco.rollout``
  call per step (``tests.native_oracle``): whole studies, compared by the bytes of the ``trials.parquet`` they
  write. The two run the same C MuJoCo ``mj_step`` on the same per-instance models from the same states, controls
  and warm starts (docs/backends.md), so nothing is allowed to differ: not a bit of any trial's figures, parameters
  or optimizer decisions, and not the states they leave. Studies are short (few trials of 0.18 s, a small optimizer)
  and cover a controller ablation and a load adaptation whose payload changes twice (a new batch of models each
  time), at batch 1, 20 and 64.
- ``ffi`` (``cpgjax.sim.ffi_step``: the step in C++, called from inside one compiled program per trial): its
  physics step, from Python and through the FFI, whole or in two overlapped parts, equals the reference's bit for
  bit for the same torques. Its
  trials do not equal the per-tick ones bit for bit: XLA compiles the controller inside the trial's loop into other
  kernels than the per-tick call, which round some results differently in the last bit (as a different number of
  XLA threads does to the per-tick call itself), and the dynamics amplify such differences. The last test bounds
  them.
"""

import jax
import numpy as np
import pytest

from cpgjax import ablation, cpg, gp
from cpgjax.go1 import model as go1_model
from cpgjax.optim import acquisition
from cpgjax.sim import ffi_step, native_physics
from cpgjax.sim import native as native_go1
from cpgjax.study import files as study_io
from cpgjax.study.spec import Change, Schedule, StudySpec
from cpgjax.trial import optimizer_setting, protocol
from tests import native_oracle

TRIAL = protocol.TrialConfig(transition_steps=60, steady_steps=120)
TRIALS = 4
needs_ffi = pytest.mark.skipif(
    not ffi_step.available(),
    reason="the native physics step could not be built here "
    "(no C++ compiler, or the build failed: see the warning it logs)",
)


def _optimizer():
    ranges = StudySpec("ranges", physics=("paper",)).optimizer_config()
    return optimizer_setting.paper_config(
        capacity=TRIALS,
        fit=gp.FitConfig(num_steps=4),
        context_lower=ranges.context_lower,
        context_upper=ranges.context_upper,
        acquisition=acquisition.AcquisitionConfig(num_candidates=16, num_restarts=1, num_steps=3),
    )


def _spec(study: str, batch: int) -> StudySpec:
    common = dict(num_trials=TRIALS, trial=TRIAL, optimizer=_optimizer(), physics=("paper",))
    if study == "controller_ablation":
        controllers = cpg.CONTROLLERS if batch % len(cpg.CONTROLLERS) == 0 else cpg.CONTROLLERS[-1:]
        return StudySpec(study, controllers=controllers, seeds=tuple(range(batch // len(controllers))), **common)
    payload = Schedule("0→7.5→15 kg", (Change(2, "payload_kg", 7.5), Change(3, "payload_kg", 15.0)))
    return StudySpec(study, seeds=tuple(range(batch)), schedules=(payload,), group_by=("schedule",), **common)


def _three_scenarios(physics: str = "paper"):
    """The physics tests' batch: three floors, slopes and payloads under the paper profile."""
    return go1_model.make_scenarios(
        friction=[0.6, 0.3, 0.9], slope_deg=[0.0, 5.0, -5.0], payload_kg=[0.0, 7.5, 15.0], physics=physics
    )


def _assert_the_reference_steps_so(ref, new, torques, outputs):
    """Each step's controller input in ``outputs`` (float32 [physics | sensor data | failed]) is what ``ref``
    gives stepped from Python with the same torques, and ``new`` (closed) ends in ``ref``'s state, bit for bit."""
    for k, torque in enumerate(torques):
        failed = ref.step(torque)
        expected = np.concatenate([ref.physics, ref.sensordata, failed[:, None]], axis=1).astype(np.float32)
        np.testing.assert_array_equal(outputs[k], expected)
    for a, b in zip(new.get_state(), ref.get_state(), strict=True):
        np.testing.assert_array_equal(a, b)
    new.close()


def _run(engine: ablation.Engine, stepping: str, out, monkeypatch):
    """The whole study with ``stepping`` (or the reference, ``native_oracle.STEPPING``, standing in for the
    backend's physics); one engine for both runs (its optimizer compiles once), whose simulator is made afresh for
    each run (``Engine.simulator`` keeps it from trial to trial)."""
    with monkeypatch.context() as patch:
        if stepping == native_oracle.STEPPING:
            patch.setattr(native_physics, "BatchPhysics", native_oracle.RolloutPhysics)
        else:
            patch.setattr(native_physics, "default_stepping", lambda: stepping)
        engine._sim = None
        result = engine.run()
        sim = engine.simulator(TRIALS - 1)
    assert sim.physics.stepping == stepping and sim.batch_size == len(result.labels)
    return study_io.write_trials(result, out).read_bytes(), result


@pytest.mark.slow
@pytest.mark.parametrize("batch", [1, 20, 64])
@pytest.mark.parametrize("study", ["controller_ablation", "load_adaptation"])
def test_a_study_writes_the_same_bytes_with_either_stepping(study, batch, tmp_path, monkeypatch):
    engine = ablation.Engine(_spec(study, batch), backend="native")
    reference, ref = _run(engine, native_oracle.STEPPING, tmp_path / "rollout.parquet", monkeypatch)
    stepped, new = _run(engine, "batch", tmp_path / "batch.parquet", monkeypatch)
    assert len(ref.labels) == batch
    if study == "load_adaptation":
        np.testing.assert_array_equal(ref.conditions.payload_kg[0], [0.0, 0.0, 7.5, 15.0])
    assert stepped == reference
    for a, b in zip(jax.tree.leaves(new.opt_state), jax.tree.leaves(ref.opt_state), strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("physics", ["paper", "paper_5khz"])
@pytest.mark.parametrize("stepping", ["batch", pytest.param("ffi", marks=needs_ffi)])
def test_every_stepping_steps_and_resets_a_diverged_instance_as_the_reference(stepping, physics, tmp_path, monkeypatch):
    """The physics alone, 200 PD-driven ticks of three scenarios with instance 1 sent to an infinite velocity at
    tick 50: every array equal bit for bit after every tick, and the diverged instance flagged once and back to
    standing; under ``paper_5khz`` a tick is five physics steps of 0.2 ms, the torques held."""
    monkeypatch.chdir(tmp_path)  # MuJoCo logs its instability warning to ./MUJOCO_LOG.TXT
    scenario = _three_scenarios(physics)
    ref, new = native_oracle.RolloutPhysics(scenario), native_physics.BatchPhysics(scenario, stepping=stepping)
    ids = go1_model.indices()
    q_stand = go1_model.standing_qpos()[ids.joint_qpos]
    flagged = []
    for k in range(200):
        if k == 50:
            for p in (ref, new):
                p.physics[1, p.layout.qvel] = np.inf
        q, dq = new.physics[:, new.layout.qpos][:, ids.joint_qpos], new.physics[:, new.layout.qvel][:, ids.joint_dof]
        torque = (60.0 * (q_stand + 0.3 * np.sin(0.03 * k) - q) - np.nan_to_num(dq, posinf=0.0, neginf=0.0)).astype(
            np.float32
        )
        failed_ref, failed_new = ref.step(torque), new.step(torque)
        np.testing.assert_array_equal(failed_new, failed_ref)
        for a, b in zip(new.get_state(), ref.get_state(), strict=True):
            np.testing.assert_array_equal(a, b)
        flagged += [k] * int(failed_new[1])
    assert flagged == [50]
    assert new.substeps == ref.substeps == (5 if physics == "paper_5khz" else 1)
    assert new.physics[0, new.layout.time] == pytest.approx(native_physics.CLOCK_START_S + 200 * 0.001)
    ref.close()
    new.close()


def test_an_unknown_stepping_is_refused_with_the_allowed_ones():
    with pytest.raises(ValueError, match=r"stepping 'threads': allowed \('ffi', 'batch'\)"):
        native_physics.BatchPhysics(go1_model.make_scenarios(friction=[0.6]), stepping="threads")


@needs_ffi
def test_the_step_called_inside_a_compiled_loop_equals_the_reference():
    """The FFI path itself: 100 steps with a random torque sequence inside one jitted ``fori_loop``
    (``ffi_step.call``), against the ``batch`` stepping from Python: every step's output is the reference's state
    packed as the controller reads it (float32 [physics | sensor data | failed]), and the states after the loop are
    equal bit for bit."""
    scenario = _three_scenarios()
    ref, new = (native_physics.BatchPhysics(scenario, stepping=s) for s in ("batch", "ffi"))
    torques = np.random.default_rng(0).normal(scale=3.0, size=(100, 3, 12)).astype(np.float32)
    shape = (3, new.layout.size + new.sensordata.shape[1] + 1)

    @jax.jit
    def run(handle, torques):
        def step(k, outputs):
            return outputs.at[k].set(ffi_step.call(handle, torques[k], shape))

        return jax.lax.fori_loop(0, len(torques), step, jax.numpy.zeros((len(torques), *shape)))

    _assert_the_reference_steps_so(ref, new, torques, np.asarray(run(new.ffi_handle, torques)))


@needs_ffi
def test_the_overlapped_steps_of_two_halves_equal_the_reference():
    """The calls of the overlapped trial (``native._run_ffi_overlapped``: ``ffi_step.alternate`` each half-tick,
    ``ffi_step.finish`` at the end) in one jitted loop, four instances in halves of two, 100 random torques: every
    half's output of every step is the reference's (the ``batch`` stepping from Python), and so are the states
    after, bit for bit, whichever thread stepped an instance."""
    scenario = go1_model.make_scenarios(
        friction=[0.6, 0.3, 0.9, 0.45],
        slope_deg=[0.0, 5.0, -5.0, 2.5],
        payload_kg=[0.0, 7.5, 15.0, 3.0],
        physics="paper",
    )
    ref, new = (native_physics.BatchPhysics(scenario, stepping=s) for s in ("batch", "ffi"))
    torques = np.random.default_rng(1).normal(scale=3.0, size=(100, 4, 12)).astype(np.float32)
    n, half, width = len(torques), 2, new.layout.size + new.sensordata.shape[1] + 1

    @jax.jit
    def run(handle, torques):
        def half_step(j, loop):
            outputs, previous = loop
            p = j % 2
            torque = jax.lax.dynamic_slice_in_dim(torques[j // 2], p * half, half)
            # computed from the last call's output, as the controller's torques are in the trial: the calls' order
            torque = jax.numpy.where(jax.numpy.isfinite(previous).all(), torque, np.nan)
            other = ffi_step.alternate(handle, torque, p, width)  # the other half after its step ⌊(j − 1)/2⌋
            return jax.numpy.where(j == 0, outputs, outputs.at[(j - 1) // 2, 1 - p].set(other)), other

        outputs, last = jax.lax.fori_loop(
            0, 2 * n, half_step, (jax.numpy.zeros((n, 2, half, width)), jax.numpy.zeros((half, width)))
        )
        outputs = outputs.at[n - 1, 1].set(ffi_step.finish(handle, last, (half, 2 * half), width))
        return outputs.reshape(n, 2 * half, width)

    _assert_the_reference_steps_so(ref, new, torques, np.asarray(run(new.ffi_handle, torques)))


@needs_ffi
def test_a_half_started_out_of_turn_is_refused_in_one_line_and_the_stepper_goes_on():
    physics = native_physics.BatchPhysics(go1_model.make_scenarios(friction=[0.6, 0.3, 0.9, 0.45]), stepping="ffi")
    width = physics.layout.size + physics.sensordata.shape[1] + 1
    second_first = jax.jit(lambda handle, torque: ffi_step.alternate(handle, torque, 1, width))
    with pytest.raises(jax.errors.JaxRuntimeError, match="cpgjax_step_alternate: a part published out of order"):
        jax.block_until_ready(second_first(physics.ffi_handle, jax.numpy.zeros((2, 12))))
    assert not physics.step(np.zeros((4, 12), np.float32)).any()
    physics.close()


@needs_ffi
def test_an_ffi_trial_follows_the_per_tick_trial_to_rounding_until_the_dynamics_amplify_it(
    native_sim, mid_params, vmc_tegotae_gates
):
    """The session batch (nominal, 15 kg, uphill, μ = 0.1, coarse, nominal) from standing, 300 logged ticks with
    each stepping from the same state: every logged quantity (state, torques, foot forces and positions, CPG, foot
    targets, attitude) agrees within 1e-4 of its size (of 1 where smaller). Measured (the ffi trial in two
    overlapped halves, ``native.overlapped``, on two cores): at most 1.0e-5 (torques), 1.0e-6 (velocities),
    1.2e-7 (positions); 3.3e-5 after 1,000 ticks. Over a trial the trajectories part further
    (contact decided a tick apart), as between the engines (docs/backends.md): the trials are samples of the same
    noisy objective."""
    logs = []
    for stepping in ("batch", "ffi"):
        sim = native_go1.NativeBackend(native_sim.scenario, trial_config=native_sim.trial_config, stepping=stepping)
        _, log = sim.rollout(sim.reset(mid_params), mid_params, vmc_tegotae_gates, num_steps=300)
        logs.append(log)
        sim.physics.close()
    for name, per_tick, fused in zip(protocol.StepLog._fields, *logs, strict=True):
        per_tick, fused = np.asarray(per_tick), np.asarray(fused)
        assert np.all(np.isfinite(fused)), name
        np.testing.assert_array_less(np.abs(fused - per_tick), 1e-4 * np.maximum(np.abs(per_tick), 1.0), err_msg=name)
