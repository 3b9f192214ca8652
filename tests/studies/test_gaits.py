"""Gaits as a parameter (docs/gaits.md): each gait's oscillators settle at the phase lags of its source, the walks step
in their named sequences, and a gait travels as data through a study (a grid axis), its files and its replay."""

import json

import numpy as np
import pyarrow.parquet as pq
import pytest

from cpgjax import ablation, cpg
from cpgjax.go1 import model as go1_model
from cpgjax.studies import driver as study_driver
from cpgjax.studies import options as study_options
from cpgjax.studies import registry
from cpgjax.study import spec as study_spec
from cpgjax.trial import params as param_space
from cpgjax.trial import protocol, tuned
from tests import test_outputs

# The phase offsets of FL, RR, RL behind FR [multiples of π], typed from the CPG-RL code of Bellegarda & Ijspeert
# (leg order FR, FL, RR, RL, as cpgjax.go1.constants.LEG_NAMES): trot, pace, bound and its walk (a diagonal
# sequence); the lateral-sequence walk is that walk negated; the pronk has every leg together.
SOURCE_OFFSETS_PI = {
    "trot": (1, 1, 0),
    "pace": (1, 0, 1),
    "bound": (0, 1, 1),
    "walk_diagonal": (1, 1.5, 0.5),
    "walk": (1, 0.5, 1.5),
    "pronk": (0, 0, 0),
}
# Each walk's footfalls after FR's, in time: the lateral sequence puts a hind foot before the fore foot of its own
# side (RL → FL → RR → FR), the diagonal one before the fore foot of the other side (RR → FL → RL → FR).
FOOTFALLS_AFTER_FR = {"walk": ("RL", "FL", "RR"), "walk_diagonal": ("RR", "FL", "RL")}
# How far a settled gait's mean phase difference may sit from the lag it is coupled to [rad]: ω_swing ≠ ω_stance
# makes the legs drift apart and back within each cycle (measured: at most 0.08 rad at the box's midpoint).
PHASE_TOLERANCE_RAD = 0.15


@pytest.fixture(scope="module")
def logs():
    """3 s of every gait, open loop at the box's midpoint on the flat floor, after one settling trial (native)."""
    names = list(cpg.GAITS)
    scenario = go1_model.make_scenarios(friction=[0.6] * len(names), physics="paper")
    params = np.tile(param_space.midpoint(), (len(names), 1))
    return dict(
        zip(
            names,
            registry.rollouts(
                params, ["open_loop"] * len(names), scenario, protocol.TrialConfig(), "native", 3000, names
            ),
            strict=True,
        )
    )


def test_every_gait_of_the_source_is_offered():
    assert set(cpg.GAITS) == set(SOURCE_OFFSETS_PI)
    with pytest.raises(ValueError, match="unknown gait 'gallop'; allowed: trot, pace"):
        cpg.controller_gates("open_loop", "gallop")


@pytest.mark.parametrize("name", list(SOURCE_OFFSETS_PI))
def test_each_gait_settles_at_its_sources_phase_differences(logs, name):
    """The steady phases' circular mean of θ_j − θ_FR, from the oscillator states of a walk in the simulator, is the
    source's offset of leg j, for every leg."""
    theta = np.asarray(logs[name].phase_rad, np.float64)  # (T, 4)
    measured = np.angle(np.mean(np.exp(1j * (theta - theta[:, :1])), axis=0))
    want = np.pi * np.array((0.0, *SOURCE_OFFSETS_PI[name]))
    error = np.angle(np.exp(1j * (measured - want)))
    assert np.all(np.abs(error) < PHASE_TOLERANCE_RAD), (name, measured, want)


@pytest.mark.parametrize("name", list(FOOTFALLS_AFTER_FR))
def test_the_walks_step_in_their_named_sequence(logs, name):
    """Touchdown (the phase entering stance, sin θ from > 0 to ≤ 0) of each leg after each of FR's: the legs come down
    in the order the walk's name says."""
    stance = np.sin(np.asarray(logs[name].phase_rad, np.float64)) <= 0.0
    touchdowns = [np.flatnonzero(~stance[:-1, leg] & stance[1:, leg]) for leg in range(4)]
    legs = ("FR", "FL", "RR", "RL")
    for t_fr in touchdowns[0][:-1]:
        after = {legs[leg]: t[t > t_fr][0] for leg, t in enumerate(touchdowns) if leg > 0}
        assert tuple(sorted(after, key=after.get)) == FOOTFALLS_AFTER_FR[name]


def test_a_file_of_the_trot_era_replays_as_a_trot(tmp_path):
    """A best_params.json without a gait (written before gaits were a choice) was tuned walking the trot."""
    path = tmp_path / "best_params.json"
    path.write_text(json.dumps({"params": param_space.as_dict(param_space.midpoint()), "controller": "tegotae"}))
    assert tuned.load(path).tuned_for == {"controller": "tegotae", "gait": "trot"}


STUDY = """name = "gaited"
trials = 2
seeds = 1
group_by = ["gait"]
[grid]
controllers = ["open_loop"]
gaits = {gaits}
physics = ["paper"]
terrain_amplitude_m = [0.0]
[trial]
transition_s = 0.0
steady_s = 0.3
"""


def _run(tmp_path, gaits):
    path = tmp_path / f"{'_'.join(gaits)}.toml"
    path.write_text(STUDY.format(gaits=json.dumps(gaits)))
    study = study_driver.read(path)
    out = tmp_path / "_".join(gaits)
    text, out, result = study_driver.run_file(
        study, study_options.RunOptions(out=out, backend="native", notify=lambda line: None)
    )
    return out, result


def test_a_gaits_axis_runs_each_gait_as_data_and_its_files_carry_it(tmp_path):
    """In one batch, each instance walks its own gait (its phase lags), the trot instance as it walks in a study of
    the trot alone; the trial table has a gait column (and, the study naming a ground axis, the ground's columns,
    every one documented) and each group's best_params names its gait."""
    out, result = _run(tmp_path, ["trot", "bound"])
    engine = ablation.Engine(result.spec, backend="native")
    np.testing.assert_array_equal(
        engine.batch.gates.phase_lag_rad[:2], np.float32([cpg.gait_phase_lags("trot"), cpg.gait_phase_lags("bound")])
    )
    table = pq.read_table(out / "trials.parquet").to_pydict()
    assert table["gait"] == ["trot", "trot", "bound", "bound"] and set(table["terrain"]) == {"flat"}
    assert test_outputs.undocumented("study trials.parquet", table) == []
    for gait in ("trot", "bound"):
        assert tuned.load(out / "best_params" / f"gait{gait}.json").tuned_for["gait"] == gait
    _, alone = _run(tmp_path, ["trot"])
    np.testing.assert_allclose(result.trials.objective[:, 0], alone.trials.objective[:, 0], rtol=1e-5)
    assert not np.allclose(result.trials.objective[:, 1], result.trials.objective[:, 0])


def test_a_study_without_gaits_has_the_trial_table_it_had(tmp_path):
    """Unset, the gaits axis is the trot alone and the trial table has no gait column (the paper's studies' tables
    stay byte for byte those of their record, tests/study/test_spec_files.py)."""
    spec = study_spec.StudySpec("plain")
    assert spec.axis("gaits") == ("trot",) and [lab["gait"] for lab in study_spec.instances(spec)] == ["trot"]
    with pytest.raises(study_spec.StudyError, match="unknown gait 'canter'; allowed: trot, pace"):
        study_spec.validate(study_spec.StudySpec("bad", gaits=("canter",)))
