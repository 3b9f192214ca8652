"""The lockstep engine: option validation, schedules, the batched run against a hand-written unbatched loop, data
reuse, sharded against unsharded, and kill → resume against an uninterrupted run.

Tiny instances throughout (short trials, small optimizer) and the native backend (C MuJoCo, compiles in seconds);
the trial and optimizer logic is the same at the paper's sizes.
"""

import dataclasses
import json
import os
import pathlib
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pyarrow.parquet as pq
import pytest

from cpgjax import ablation, gp
from cpgjax.optim import acquisition, bo
from cpgjax.sim import native as native_go1
from cpgjax.study import files as study_io
from cpgjax.study import placement as study_placement
from cpgjax.study import spec as study_spec
from cpgjax.study.spec import Change, Schedule, StudyError, StudySpec
from cpgjax.trial import objective, optimizer_setting, protocol
from cpgjax.trial import params as param_space

TRIAL = protocol.TrialConfig(transition_steps=100, steady_steps=200)
TRIALS = 5


def small_optimizer(capacity=TRIALS):
    # The soft physics profile's context ranges (docs/decisions.md §11), which these studies simulate.
    ranges = StudySpec("ranges").optimizer_config()
    return optimizer_setting.paper_config(
        capacity=capacity,
        fit=gp.FitConfig(num_steps=8),
        context_lower=ranges.context_lower,
        context_upper=ranges.context_upper,
        acquisition=acquisition.AcquisitionConfig(num_candidates=32, num_restarts=2, num_steps=5),
    )


def tiny_spec(**overrides):
    settings = dict(
        name="tiny",
        num_trials=TRIALS,
        controllers=("open_loop", "vmc_tegotae"),
        seeds=(0, 1),
        trial=TRIAL,
        optimizer=small_optimizer(),
        schedules=(Schedule("load", (Change(3, "payload_kg", 7.5),)),),
    )
    settings.update(overrides)
    return StudySpec(**settings)


# The kill/resume and sharding subprocesses build the same study from this source.
SPEC_SOURCE = """
from cpgjax import ablation
from cpgjax.study import placement as study_placement
from cpgjax.optim import acquisition
from cpgjax.optim import bo
from cpgjax import gp
from cpgjax.study import spec as study_spec
from cpgjax.trial import optimizer_setting, protocol
spec = study_spec.StudySpec(
    name="tiny", num_trials=5, controllers=("open_loop", "vmc_tegotae"), seeds=(0, 1),
    trial=protocol.TrialConfig(transition_steps=100, steady_steps=200),
    optimizer=optimizer_setting.paper_config(capacity=5, fit=gp.FitConfig(num_steps=8),
                                             context_lower=study_spec.StudySpec("ranges").optimizer_config().context_lower,
                                             context_upper=study_spec.StudySpec("ranges").optimizer_config().context_upper,
                                             acquisition=acquisition.AcquisitionConfig(
                                                num_candidates=32, num_restarts=2, num_steps=5)),
    schedules=(study_spec.Schedule("load", (study_spec.Change(3, "payload_kg", 7.5),)),))
"""


@pytest.fixture(scope="module")
def engine():
    return ablation.Engine(tiny_spec(), backend="native")


@pytest.fixture(scope="module")
def uninterrupted(engine):
    return engine.run()


# ----------------------------------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    "overrides, message",
    [
        (dict(controllers=("open_loop", "cpg_plus")), "unknown controller 'cpg_plus'"),
        (dict(seeds=(-1,)), "seed -1"),
        (dict(num_trials=0), "num_trials = 0"),
        (dict(friction=()), "grid axis friction is empty"),
        (dict(seeds=(0, 0)), "duplicates"),
        (dict(schedules=(Schedule("x", (Change(9, "payload_kg", 5.0),)),)), "change at trial 9 outside [0, 5)"),
        (dict(schedules=(Schedule("x", (Change(1, "mass", 5.0),)),)), "unknown field 'mass'"),
        (dict(schedules=(Schedule("x", (Change(2, "payload_kg", -3.0),)),)), "trial 2: payload_kg = -3.0 is outside"),
        (dict(slope_deg=(50.0,)), "slope_deg = 50.0"),
        (dict(target_velocity_mps=(0.0,)), "target_velocity_mps = 0.0 is outside the allowed range (0, 2]"),
        (dict(friction=(5.0,)), "friction = 5.0 is outside the allowed range [0.1, 1.5]"),
        (dict(optimizer=small_optimizer(capacity=3)), "capacity 3 < num_trials 5"),
        (dict(max_trials=4), "max_trials = 4; need an integer in [num_trials = 5, 1000]"),
        (dict(group_by=("colour",)), "group_by 'colour'"),
    ],
)
def test_bad_options_fail_before_compute_with_a_clear_message(overrides, message):
    with pytest.raises(StudyError, match=None) as err:
        ablation.Engine(tiny_spec(**overrides), backend="native")
    assert message in str(err.value) and "'tiny'" in str(err.value)


def test_grid_order_and_schedules():
    spec = tiny_spec(
        friction=(0.3, 0.9),
        schedules=(
            Schedule("a", (Change(2, "payload_kg", 7.5), Change(4, "payload_kg", 15.0), Change(3, "inference", 1))),
            Schedule("b", (Change(1, "target_velocity_mps", 0.3),)),
        ),
    )
    labels = study_spec.instances(spec)
    assert len(labels) == 2 * 2 * 2 * 2
    assert labels[0] == dict(
        controller="open_loop",
        gait="trot",
        seed=0,
        friction=0.3,
        slope_deg=0.0,
        payload_kg=0.0,
        target_velocity_mps=0.5,
        schedule="a",
        data_reuse=True,
        physics="paper",
        terrain_amplitude_m=0.0,
        terrain_seed=0,
        foot_friction=-1.0,
    )
    assert labels[1]["schedule"] == "b" and labels[2]["friction"] == 0.9 and labels[4]["seed"] == 1
    cond = study_spec.conditions(spec)
    np.testing.assert_array_equal(cond.payload_kg[0], [0, 0, 7.5, 7.5, 15])
    np.testing.assert_array_equal(cond.inference[0], [0, 0, 0, 1, 1])
    np.testing.assert_array_equal(cond.target_velocity_mps[1], [0.5, 0.3, 0.3, 0.3, 0.3])
    np.testing.assert_array_equal(cond.friction[2], [0.9] * 5)


def test_placement_pads_to_the_device_count():
    devices = jax.devices()
    placement = study_placement.make_placement(3, devices)
    assert placement.padded_size % len(devices) == 0 and placement.padded_size >= 3
    x = np.arange(placement.padded_size * 2.0).reshape(-1, 2)
    np.testing.assert_array_equal(study_placement.fetch(placement.put(x)), x)


# ----------------------------------------------------------------------------------------------- the run


def _ucb(config, state, context, beta, x):
    """The UCB acquisition (eq. 8) of the optimizer ``state`` at parameters x (P,) and a context (C,)."""
    lower, width = np.asarray(config.parameter_lower), np.asarray(config.parameter_upper) - config.parameter_lower
    c_lower = np.asarray(config.context_lower)
    c_width = np.asarray(config.context_upper) - c_lower
    dataset = gp.Dataset(
        jnp.concatenate([(state.parameters - lower) / width, (state.contexts - c_lower) / c_width], 1).astype(
            jnp.float32
        ),
        state.objectives,
        state.stored,
    )
    post = gp.posterior(state.gp_params, dataset, jnp.ones(10, bool), 2)
    query = jnp.concatenate([(x - lower) / width, (np.asarray(context) - c_lower) / c_width])[None].astype(jnp.float32)
    return float(acquisition.upper_confidence_bound(post, query, acquisition.ucb_multiplier(beta, "paper"), 2)[0])


def test_engine_equals_a_hand_written_unbatched_loop(engine, uninterrupted):
    """Instance 3 (vmc_tegotae, seed 1) of the batch vs Algorithm 1 written out for that instance alone: unbatched
    propose / a batch-1 simulator / observe, the same keys fold_in(PRNGKey(seed), trial), the same schedule.

    The random proposals agree to float rounding. A UCB proposal is an argmax that float rounding between a batched
    and an unbatched program can move to another, equally good point: there the engine's proposal must reach the
    acquisition of the hand-written one (within 1e-3 of its magnitude), and the loop continues from the engine's."""
    b, seed = 3, 1
    assert engine.labels[b]["controller"] == "vmc_tegotae" and engine.labels[b]["seed"] == seed
    config = small_optimizer()
    opt = bo.make_optimizer(config)
    state = opt.init(active_dims=jnp.ones(8, bool))
    context = jnp.asarray(engine.initial_context()[0])
    gates = protocol.batch_gates(["vmc_tegotae"])
    sim, sim_state, payload = None, None, None
    for t in range(TRIALS):
        x = np.asarray(opt.propose(state, context, jax.random.fold_in(jax.random.PRNGKey(seed), t)), np.float64)
        if t >= config.num_random_proposals:
            ours, theirs = uninterrupted.trials.params[t, b], x
            beta = float(opt.beta(state, context).beta)
            assert _ucb(config, state, context, beta, ours) >= _ucb(config, state, context, beta, theirs) - 1e-3 * abs(
                _ucb(config, state, context, beta, theirs)
            )
            x = ours
        x = x[None]
        new_payload = 7.5 if t >= 3 else 0.0
        if new_payload != payload:
            from cpgjax.go1 import model as go1_model

            sim = native_go1.NativeBackend(go1_model.make_scenarios(payload_kg=[new_payload]), trial_config=TRIAL)
            payload = new_payload
        if sim_state is None:
            sim_state = sim.reset(x)
        sim_state, record = sim.trial(sim_state, x, gates)
        one = jax.tree.map(lambda a: a[0], record)
        j = objective.objective(one, 0.5)
        measured = objective.context(one)
        # The GP sees the context clipped to the optimizer's ranges (docs/decisions.md §11); the log keeps it raw.
        # A trial that fell keeps the context it was proposed for.
        config = small_optimizer()
        if not (float(one.fell) > 0 or float(one.failed) > 0):
            context = jnp.clip(measured, jnp.asarray(config.context_lower), jnp.asarray(config.context_upper))
        state, _ = opt.observe(state, jnp.asarray(x[0], jnp.float32), context, j)
        np.testing.assert_allclose(uninterrupted.trials.params[t, b], x[0], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(uninterrupted.trials.objective[t, b], float(j), rtol=1e-4, atol=1e-5)
        np.testing.assert_allclose(uninterrupted.trials.context[t, b], np.asarray(measured), rtol=1e-4, atol=1e-5)
    assert uninterrupted.trials.objective.shape == (TRIALS, 4)
    # σ_N is masked out without Tegotae (docs/decisions.md §13): the proposal holds the box midpoint.
    sigma = uninterrupted.trials.params[:, 0, param_space.SIGMA_N_INDEX]
    np.testing.assert_allclose(sigma, param_space.midpoint()[param_space.SIGMA_N_INDEX], rtol=1e-6)
    assert np.all(np.isfinite(uninterrupted.trials.objective))
    # the payload change shows in the measured mass and context
    np.testing.assert_allclose(
        uninterrupted.trials.total_mass_kg[3:] - uninterrupted.trials.total_mass_kg[:1], 7.5, atol=1e-3
    )


def test_target_change_reuses_data_or_restarts():
    spec = tiny_spec(
        controllers=("vmc_tegotae",),
        seeds=(0,),
        data_reuse=(True, False),
        schedules=(Schedule("v", (Change(3, "target_velocity_mps", 0.3),)),),
    )
    engine = ablation.Engine(spec, backend="native")
    assert engine.batch.uses_records
    result = engine.run()
    st = result.opt_state
    reuse = [lab["data_reuse"] for lab in result.labels].index(True)
    restart = 1 - reuse
    # data reuse: every stored J recomputed for the new target from the stored records (paper Sec. III-A-2)
    recomputed = jax.vmap(objective.objective, in_axes=(0, None))(
        jax.tree.map(lambda a: a[reuse], st.records), jnp.float32(0.3)
    )
    np.testing.assert_allclose(st.objectives[reuse, :TRIALS], np.asarray(recomputed)[:TRIALS], rtol=1e-5)
    assert int(st.num_stored[reuse]) == TRIALS and float(st.target_velocity[reuse]) == pytest.approx(0.3)
    # without reuse the optimizer restarted at the change: only the trials since then are stored
    assert int(st.num_stored[restart]) == TRIALS - 3
    np.testing.assert_allclose(st.objectives[restart, :2], result.trials.objective[3:, restart], rtol=1e-5)
    # the two instances share seed and history until the change
    np.testing.assert_array_equal(result.trials.params[:3, 0], result.trials.params[:3, 1])


def _run_subprocess(code: str, env_extra: dict | None = None, timeout=240):
    env = dict(os.environ, JAX_PLATFORMS="cpu", **(env_extra or {}))
    return subprocess.run(
        [sys.executable, "-c", code],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=pathlib.Path(__file__).resolve().parents[1],
    )


def test_sharded_over_two_devices_equals_one_device():
    code = (
        SPEC_SOURCE
        + """
import dataclasses, jax, json, numpy as np
spec = dataclasses.replace(spec, seeds=(0, 1, 2), controllers=("vmc_tegotae",), num_trials=4)  # 3: padded to 4
assert len(jax.devices()) == 2
two = ablation.Engine(spec, backend="native").run()
one = ablation.Engine(spec, backend="native", devices=jax.devices()[:1]).run()
assert len(two.devices) == 2 and len(one.devices) == 1
print(json.dumps(dict(
    params=float(np.abs(two.trials.params - one.trials.params).max()),
    objective=float(np.abs(two.trials.objective - one.trials.objective).max()),
    shape=list(two.trials.objective.shape))))
"""
    )
    out = _run_subprocess(code, {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"})
    assert out.returncode == 0, out.stderr[-3000:]
    diff = json.loads(out.stdout.strip().splitlines()[-1])
    assert diff["shape"] == [4, 3]
    assert diff["params"] <= 1e-5 and diff["objective"] <= 1e-4, diff


def test_progress_pace_and_eta_leave_out_the_first_trial(engine, uninterrupted, monkeypatch):
    """The first trial of a run compiles: the ETA waits for the second and takes the pace of the later trials."""
    delays = iter([1.0] + [0.05] * (TRIALS - 1))  # a slow (compiling) first trial, then quick ones
    first = uninterrupted.trials

    def fake_trial(run, t):
        time.sleep(next(delays))
        log = study_io.TrialLog(*(np.asarray(getattr(first, name)[t]) for name in study_io.TrialLog._fields))
        return run._replace(logs=run.logs + [log])

    monkeypatch.setattr(engine, "_trial", fake_trial)
    progress = []
    engine.run(progress=progress.append)
    assert [p.trial for p in progress] == list(range(1, TRIALS + 1)) and progress[0].eta_s is None
    assert progress[1].eta_s == pytest.approx((TRIALS - 2) * 0.05, abs=0.1)  # not the first trial's 1 s
    assert progress[-1].eta_s == 0.0


def test_killed_study_resumes_to_the_uninterrupted_result(tmp_path, uninterrupted):
    out = tmp_path / "study"
    code = (
        SPEC_SOURCE
        + f"""
ablation.Engine(spec, backend="native").run({str(out)!r})
"""
    )
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    proc = subprocess.Popen(
        [sys.executable, "-c", code],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        cwd=pathlib.Path(__file__).resolve().parents[1],
    )
    ckpt = out / study_io.CHECKPOINT
    deadline = time.time() + 240
    done = 0
    while time.time() < deadline and proc.poll() is None:
        if ckpt.exists():
            try:
                with np.load(ckpt) as z:
                    done = json.loads(bytes(z["meta"]).decode())["trial"]
            except (OSError, ValueError, KeyError):
                done = 0
            if done >= 2:
                break
        time.sleep(0.05)
    proc.kill()
    proc.wait()
    assert 2 <= done < TRIALS, f"expected to kill mid-study, got {done} trials done (rc {proc.returncode})"
    left = study_io.load_checkpoint(out, tiny_spec())
    # the optimizer's observation buffers are kept up to the trials run, not to its capacity (bo.first_rows)
    assert left.opt_leaves[0].shape == (4, left.trial, 8) and left.trial < tiny_spec().optimizer_config().capacity
    resumed = ablation.Engine(tiny_spec(), backend="native").run(out, resume=True)
    for name in study_io.TrialLog._fields:
        np.testing.assert_array_equal(getattr(resumed.trials, name), getattr(uninterrupted.trials, name), name)
    for a, b in zip(jax.tree.leaves(resumed.opt_state), jax.tree.leaves(uninterrupted.opt_state), strict=True):
        np.testing.assert_array_equal(a, b)
    # resuming a different study from this folder is refused
    with pytest.raises(StudyError, match="different study"):
        ablation.Engine(tiny_spec(seeds=(0, 1, 2)), backend="native").run(out, resume=True)


def test_programs_loaded_from_an_earlier_runs_cache_give_the_same_study(tmp_path, uninterrupted):
    """Two processes run the study with the cache of compiled programs (``compile_cache.enable``): the first
    compiles and keeps its programs, the second loads every one of them and compiles none (``metadata.json``), and
    both give the trial logs of this process's own compilation (no cache) bit for bit."""
    counts = []
    for run in ("first", "second"):
        (tmp_path / run).mkdir()
        code = (
            SPEC_SOURCE
            + f"""
from cpgjax import compile_cache
from cpgjax.study import files as study_io
compile_cache.enable()
result = ablation.Engine(spec, backend="native").run()
study_io.write_trials(result, {str(tmp_path / run / "trials.parquet")!r})
study_io.write_metadata(result, {str(tmp_path / run / "metadata.json")!r})
"""
        )
        done = _run_subprocess(code, {"JAX_COMPILATION_CACHE_DIR": str(tmp_path / "programs")})
        assert done.returncode == 0, done.stderr[-2000:]
        counts.append(json.loads((tmp_path / run / "metadata.json").read_text())["compiled_programs"])
        columns = study_io.read_trials(tmp_path / run / "trials.parquet")
        for column, field in (
            ("objective", "objective"),
            ("cost_of_transport", "cot"),
            ("energy_j", "energy_j"),
            ("distance_m", "distance_m"),
        ):
            np.testing.assert_array_equal(columns[column], getattr(uninterrupted.trials, field), f"{run}: {column}")
    assert counts[0]["compiled"] > 0 and counts[0]["loaded"] == 0, counts
    assert counts[1] == {"loaded": counts[0]["compiled"], "compiled": 0}, counts
    assert (tmp_path / "first" / "trials.parquet").read_bytes() == (tmp_path / "second" / "trials.parquet").read_bytes()


def test_max_trials_is_the_capacity_of_the_papers_optimizer():
    assert StudySpec("s", num_trials=12).optimizer_config().capacity == 12
    assert StudySpec("s", num_trials=12, max_trials=40).optimizer_config().capacity == 40


def test_a_finished_study_extended_to_more_trials_equals_a_run_of_that_many(tmp_path, uninterrupted):
    """A run of 4 trials whose optimizers hold 5 (``max_trials``; here the explicit optimizer's capacity), then
    ``--resume`` with 5 trials: the same trial logs and optimizer state, bit for bit, as a run of 5 from the start."""
    out = tmp_path / "study"
    ablation.Engine(tiny_spec(num_trials=TRIALS - 1), backend="native").run(out)
    extended = ablation.Engine(tiny_spec(), backend="native").run(out, resume=True)
    for name in study_io.TrialLog._fields:
        np.testing.assert_array_equal(getattr(extended.trials, name), getattr(uninterrupted.trials, name), name)
    for a, b in zip(jax.tree.leaves(extended.opt_state), jax.tree.leaves(uninterrupted.opt_state), strict=True):
        np.testing.assert_array_equal(a, b)


def test_trials_on_the_ramp_walk_the_slope_of_the_distance_climbed(tmp_path):
    """Trials 2… walk a ramp: each starts on the ramp's slope at the distance climbed since trial 2 (each trial's
    steady-phase distance scaled to the whole trial, 4.5 / 3 here 300 / 200 ticks), back at the bottom after a fall,
    recomputed here from the written trials.parquet alone."""
    ramp = study_spec.Ramp(start_deg=2.0, end_deg=6.0, length_m=0.5)
    spec = tiny_spec(schedules=(Schedule("ramp", (Change(2, "ramp", 1.0),)),), ramp=ramp)
    result = ablation.Engine(spec, backend="native").run()
    study_io.write_trials(result, tmp_path / "trials.parquet")
    table = pq.read_table(tmp_path / "trials.parquet").to_pandas()
    for _, rows in table.groupby("instance"):
        rows = rows.sort_values("trial")
        assert list(rows.ramp) == [False, False, True, True, True] and (rows.slope_deg[:2] == 0.0).all()
        climbed, expected = 0.0, []
        for distance, fell in zip(rows.distance_m[2:], rows.fell[2:], strict=True):
            expected.append(ramp.start_deg + (ramp.end_deg - ramp.start_deg) * min(climbed / ramp.length_m, 1.0))
            climbed = 0.0 if fell else max(climbed + distance * 300 / 200, 0.0)
        np.testing.assert_allclose(rows.slope_deg[2:], expected, rtol=0, atol=1e-9)
    assert table.slope_deg[table.ramp].max() > ramp.start_deg  # some instance climbed
    # the result keeps the study's planned conditions; the slopes walked are their own field, the table's
    np.testing.assert_array_equal(result.conditions.slope_deg, study_spec.conditions(spec).slope_deg)
    np.testing.assert_array_equal(table.slope_deg, result.walked.slope_deg.reshape(-1))  # instance-major
    # a run stopped on the ramp and resumed (here: extended from 4 trials) records the slopes of the same walk
    out = tmp_path / "resumed"
    ablation.Engine(dataclasses.replace(spec, num_trials=4), backend="native").run(out)
    resumed = ablation.Engine(spec, backend="native").run(out, resume=True)
    np.testing.assert_array_equal(resumed.walked.slope_deg, result.walked.slope_deg)


def test_a_ramp_schedule_needs_a_ramp():
    with pytest.raises(StudyError, match="puts trials on the ramp, and the study defines none"):
        study_spec.validate(tiny_spec(schedules=(Schedule("ramp", (Change(2, "ramp", 1.0),)),)))


def test_mjx_scenario_switch_keeps_the_compiled_trial(short_sim, mid_params, vmc_tegotae_gates):
    """A payload / slope schedule with the MJX backend: ``with_scenario`` swaps the model data, not the program."""
    from cpgjax.go1 import model as go1_model

    state = short_sim.reset(mid_params)
    state, before = short_sim.trial(state, mid_params, vmc_tegotae_gates)
    compiled = short_sim._trial._cache_size()
    batch = short_sim.batch_size
    heavier = short_sim.with_scenario(go1_model.make_scenarios(payload_kg=np.full(batch, 7.5)))
    state, after = heavier.trial(state, mid_params, vmc_tegotae_gates)
    assert heavier._trial._cache_size() == compiled
    np.testing.assert_allclose(
        np.asarray(after.total_mass_kg),
        go1_model.make_scenarios().payload_kg[0]
        + np.asarray(before.total_mass_kg)
        - short_sim.scenario.payload_kg
        + 7.5,
        rtol=1e-5,
    )
    assert short_sim.scenario.payload_kg.max() == 15.0  # the original backend is unchanged


def test_a_fallen_trial_is_learned_at_the_context_it_was_proposed_for():
    """On 30° every instance falls in some trial. A fallen robot's feet carry nothing (its measured c_load is a few N),
    so the optimizer stores a fallen trial at the context its parameters were proposed for, the previous trial's (the
    middle of the ranges for trial 0), as the robot's optimizer does with a stopped trial (docs/decisions.md §11); every
    other trial at its measured context, clipped to the ranges. The trial log keeps what was measured."""
    steep = ablation.Engine(tiny_spec(slope_deg=(30.0,)), backend="native")
    result = steep.run()
    tr, config = result.trials, small_optimizer()
    fell = (tr.fell > 0) | (tr.failed > 0)
    assert fell.any(axis=0).all() and not fell.all(axis=0).any()
    assert np.median(tr.context[..., 0][fell]) < config.context_lower[0]  # what a fallen trial measures
    stored = np.swapaxes(result.opt_state.contexts[:, :TRIALS], 0, 1)  # (trials, instances, 2)
    proposed_for = np.asarray(steep.initial_context())
    for t in range(TRIALS):
        measured = np.clip(tr.context[t], config.context_lower, config.context_upper)
        expected = np.where(fell[t][:, None], proposed_for, measured)
        np.testing.assert_allclose(stored[t], expected, rtol=1e-6, atol=1e-6)
        proposed_for = expected


def test_safe_study_stores_each_trials_margin_and_shares_the_random_start(uninterrupted):
    """``StudySpec.safe``: every instance's optimizer stores the trial's safety margin as the trial log records it,
    and trial 0, random in both, is the unconstrained run's (docs/decisions.md §17)."""
    safe = ablation.Engine(tiny_spec(safe=True), backend="native")
    assert safe.optimizer_config.safe and not uninterrupted.spec.safe
    result = safe.run()
    tr = result.trials
    np.testing.assert_array_equal(tr.params[0], uninterrupted.trials.params[0])
    stored = result.opt_state.margins[:, :TRIALS].T  # (trials, instances)
    np.testing.assert_array_equal(stored[tr.accepted > 0], tr.safety_margin[tr.accepted > 0].astype(np.float32))
    assert np.all(np.isfinite(tr.safety_margin)) and np.all(tr.safety_margin <= 1.0 + 1e-6)
    assert tr.safe_fallback.shape == tr.fell.shape
    np.testing.assert_array_equal(tr.fell > 0, (tr.fell > 0) & (tr.safety_margin < 0))  # a fall is unsafe
