"""The native backend's in-place stepping (``mujoco.batch``) against its reference, one ``mujoco.rollout`` call per
step (``cpgjax.sim.native.STEPPINGS``): whole studies, compared by the bytes of the ``trials.parquet`` they write.

The two steppings run the same C MuJoCo ``mj_step`` on the same per-instance models from the same states, controls
and warm starts (docs/backends.md), so nothing is allowed to differ: not a bit of any trial's figures, parameters or
optimizer decisions, and not the states they leave. Studies are short (few trials of 0.18 s, a small optimizer)
and cover a controller ablation and a load adaptation whose payload changes twice (a new batch of models each
time), at batch 1, 20 and 64.
"""

import jax
import numpy as np
import pytest

from cpgjax import ablation, cpg, gp
from cpgjax.go1 import model as go1_model
from cpgjax.optim import acquisition
from cpgjax.sim import native as native_go1
from cpgjax.study import files as study_io
from cpgjax.study.spec import Change, Schedule, StudySpec
from cpgjax.trial import optimizer_setting, protocol

TRIAL = protocol.TrialConfig(transition_steps=60, steady_steps=120)
TRIALS = 4


def _optimizer():
    ranges = StudySpec("ranges", physics=("paper",)).optimizer_config()
    return optimizer_setting.paper_config(capacity=TRIALS, fit=gp.FitConfig(num_steps=4),
                                          context_lower=ranges.context_lower, context_upper=ranges.context_upper,
                                          acquisition=acquisition.AcquisitionConfig(num_candidates=16, num_restarts=1,
                                                                                   num_steps=3))


def _spec(study: str, batch: int) -> StudySpec:
    common = dict(num_trials=TRIALS, trial=TRIAL, optimizer=_optimizer(), physics=("paper",))
    if study == "controller_ablation":
        controllers = cpg.CONTROLLERS if batch % len(cpg.CONTROLLERS) == 0 else cpg.CONTROLLERS[-1:]
        return StudySpec(study, controllers=controllers, seeds=tuple(range(batch // len(controllers))), **common)
    payload = Schedule("0→7.5→15 kg", (Change(2, "payload_kg", 7.5), Change(3, "payload_kg", 15.0)))
    return StudySpec(study, seeds=tuple(range(batch)), schedules=(payload,), group_by=("schedule",), **common)


def _run(engine: ablation.Engine, stepping: str, out, monkeypatch):
    """The whole study with ``stepping``; one engine for both steppings (its optimizer compiles once), whose
    simulator is made afresh for each run (``Engine.simulator`` keeps it from trial to trial)."""
    monkeypatch.setattr(native_go1, "DEFAULT_STEPPING", stepping)
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
    reference, ref = _run(engine, "rollout", tmp_path / "rollout.parquet", monkeypatch)
    stepped, new = _run(engine, "batch", tmp_path / "batch.parquet", monkeypatch)
    assert len(ref.labels) == batch
    if study == "load_adaptation":
        np.testing.assert_array_equal(ref.conditions.payload_kg[0], [0.0, 0.0, 7.5, 15.0])
    assert stepped == reference
    for a, b in zip(jax.tree.leaves(new.opt_state), jax.tree.leaves(ref.opt_state), strict=True):
        np.testing.assert_array_equal(a, b)


def test_both_steppings_step_and_reset_a_diverged_instance_alike(tmp_path, monkeypatch):
    """The physics alone, 200 PD-driven steps of three scenarios with instance 1 sent to an infinite velocity at
    step 50: every array equal bit for bit after every step, and the diverged instance flagged once and back to
    standing."""
    monkeypatch.chdir(tmp_path)  # MuJoCo logs its instability warning to ./MUJOCO_LOG.TXT
    scenario = go1_model.make_scenarios(friction=[0.6, 0.3, 0.9], slope_deg=[0.0, 5.0, -5.0],
                                        payload_kg=[0.0, 7.5, 15.0], physics="paper")
    ref, new = (native_go1.BatchPhysics(scenario, stepping=s) for s in ("rollout", "batch"))
    ids = go1_model.indices()
    q_stand = go1_model.standing_qpos()[ids.joint_qpos]
    flagged = []
    for k in range(200):
        if k == 50:
            for p in (ref, new):
                p.physics[1, p.layout.qvel] = np.inf
        q, dq = new.physics[:, new.layout.qpos][:, ids.joint_qpos], new.physics[:, new.layout.qvel][:, ids.joint_dof]
        torque = (60.0 * (q_stand + 0.3 * np.sin(0.03 * k) - q)
                  - np.nan_to_num(dq, posinf=0.0, neginf=0.0)).astype(np.float32)
        failed_ref, failed_new = ref.step(torque), new.step(torque)
        np.testing.assert_array_equal(failed_new, failed_ref)
        for a, b in zip(new.get_state(), ref.get_state(), strict=True):
            np.testing.assert_array_equal(a, b)
        flagged += [k] * int(failed_new[1])
    assert flagged == [50]
    ref.close()


def test_an_unknown_stepping_is_refused_with_the_allowed_ones():
    with pytest.raises(ValueError, match=r"stepping 'threads': allowed \('batch', 'rollout'\)"):
        native_go1.BatchPhysics(go1_model.make_scenarios(friction=[0.6]), stepping="threads")
