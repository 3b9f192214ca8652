"""The feet's μ as a scenario field of its own, and a floor μ the feet do not feel said once: the paper's Gazebo floor
and feet are two surfaces, and a contact takes the smaller μ (gazebo-classic ODEPhysics::Collide); unitree_ros
gives the feet 0.6 (go1_description gazebo.xacro, the ``paper`` profile's ``foot_friction``)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from cpgjax import cli, mjx_go1
from cpgjax.go1 import model as go1_model
from cpgjax.studies import options as study_options
from cpgjax.study import spec as study_spec

IDS = go1_model.indices()
UNITREE_ROS_FEET_MU = 0.6  # go1_description gazebo.xacro: mu1 = mu2 = 0.6 on each foot
PAPER_09 = "friction above 0.6 under physics paper walks as 0.6 (asked: 0.9)"  # a note's first clause


@pytest.fixture
def notes(caplog):
    """The model's warnings in this test, which sees its own first time of each note."""
    go1_model._SAID.clear()
    caplog.set_level(logging.WARNING, logger=go1_model.log.name)
    yield caplog
    go1_model._SAID.clear()


def _lines(notes) -> list[str]:
    return [r.getMessage() for r in notes.records if r.name == go1_model.log.name]


def test_the_contact_takes_the_smaller_mu_of_floor_and_feet_in_both_backends():
    floor = [0.9, 0.9, 0.9, 0.3, 0.9, 0.9]
    feet = [-1.0, 1.2, 0.4, 1.2, -1.0, 0.4]
    physics = ["paper"] * 4 + ["soft", "soft"]
    scenario = go1_model.make_scenarios(friction=floor, foot_friction=feet, physics=physics)
    # typed out: paper's own feet 0.6; feet of 1.2 let the floor's 0.9 count; feet of 0.4 cap it; the floor's 0.3
    # below any feet; soft's feet have no μ (MuJoCo's floor priority) unless the scenario gives them one
    expected = [UNITREE_ROS_FEET_MU, 0.9, 0.4, 0.3, 0.9, 0.4]
    np.testing.assert_array_equal(go1_model.effective_friction(scenario), expected)
    c_models = [go1_model.scenario_model(scenario, i).geom_friction[IDS.floor_geom, 0] for i in range(len(floor))]
    np.testing.assert_array_equal(c_models, expected)
    batch = mjx_go1.make_batch_model(scenario)
    np.testing.assert_allclose(np.asarray(batch.model.geom_friction[:, IDS.floor_geom, 0]), expected, rtol=1e-6)


@pytest.mark.parametrize("bad", [0.0, -0.5, np.nan, np.inf])
def test_a_foot_friction_neither_the_profiles_nor_positive_is_refused_in_one_line(bad):
    with pytest.raises(
        ValueError,
        match=r"^scenario foot_friction = .* \(instance 1\) is outside the allowed range "
        r"-1 \(the profile's\) or \(0, inf\)$",
    ):
        go1_model.make_scenarios(friction=[0.6, 0.6], foot_friction=[-1.0, bad])


def test_a_floor_above_the_feet_mu_is_said_once_with_the_mu_in_effect(notes):
    go1_model.make_scenarios(friction=[0.3, 0.6, 0.9, 0.9], physics="paper")
    go1_model.make_scenarios(friction=[0.9], physics="paper")  # the same again: nothing more
    lines = _lines(notes)
    assert len(lines) == 1, lines
    assert lines[0].startswith(
        "friction above 0.6 under physics paper walks as 0.6 (asked: 0.9): a contact takes the "
        "smaller μ of floor and feet"
    )
    assert "the feet's is 0.6 (the paper profile's feet)" in lines[0] and "--foot-friction" in lines[0]


def test_many_floors_above_the_feet_make_one_line(notes):
    go1_model.make_scenarios(friction=np.linspace(0.65, 0.95, 7), physics="paper")
    go1_model.make_scenarios(friction=[1.2], physics="paper")  # the same profile and feet: said already
    go1_model.make_scenarios(friction=[1.2], physics="soft", foot_friction=1.0)
    lines = _lines(notes)
    assert len(lines) == 2, lines
    assert "(asked: 7 values from 0.65 to 0.95)" in lines[0]
    assert lines[1].startswith("friction above 1 under physics soft walks as 1 (asked: 1.2)")
    assert "(the scenario's foot_friction)" in lines[1]


@pytest.mark.parametrize(
    "fields",
    [
        dict(friction=[0.9], physics="soft"),  # MuJoCo's rule: the floor's μ
        dict(friction=[0.6], physics="paper"),  # at the feet's, nothing lost
        dict(friction=[0.9], physics="paper", foot_friction=1.0),
    ],
)
def test_nothing_is_said_where_the_floor_counts(fields, notes):
    go1_model.make_scenarios(**fields)
    assert _lines(notes) == []


def test_a_study_says_it_before_any_compute_and_its_grid_sets_the_feet(notes, tmp_path):
    spec = study_spec.StudySpec("mu", num_trials=2, friction=(0.6, 0.9), physics=("paper",))
    study_spec.validate(spec)
    assert [line.split("):")[0] + ")" for line in _lines(notes)] == [PAPER_09]
    notes.clear()
    path = tmp_path / "feet.toml"
    path.write_text('name = "feet"\ntrials = 2\n[grid]\nfriction = [0.6, 0.9]\nfoot_friction = [1.0]\n')
    feet = study_spec.load(path)
    study_spec.validate(feet)
    assert _lines(notes) == []
    assert [lab["foot_friction"] for lab in study_spec.instances(feet)] == [1.0, 1.0]
    path.write_text('name = "feet"\ntrials = 2\n[grid]\nfoot_friction = [0.05]\n')
    with pytest.raises(study_spec.StudyError, match="grid.foot_friction"):
        study_spec.load(path)


def test_walk_prints_the_mu_in_effect_beside_the_asked_one(capsys, notes):
    assert cli.main(["walk", "--controllers", "open_loop", "--friction", "0.6,0.9", "--trials", "1"]) == 0
    out, _ = capsys.readouterr()
    assert [line.split("):")[0] + ")" for line in _lines(notes)] == [PAPER_09]
    notes.clear()
    rows = [[c.strip() for c in line.split("|")] for line in out.splitlines() if line.startswith(("| 0 |", "| 1 |"))]
    assert [r[5:7] for r in rows] == [["0.6", "0.6"], ["0.9", "0.6"]]
    assert rows[0][10:14] == rows[1][10:14]  # v_x, CoT, J, c_load: the 0.9 floor walked as the 0.6 one
    assert (
        cli.main(["walk", "--controllers", "open_loop", "--friction", "0.9", "--foot-friction", "1.0", "--trials", "1"])
        == 0
    )
    out, _ = capsys.readouterr()
    assert _lines(notes) == []
    row = [c.strip() for c in next(line for line in out.splitlines() if line.startswith("| 0 |")).split("|")]
    assert row[5:7] == ["0.9", "0.9"]
    assert row[10:14] != rows[1][10:14]  # feet of 1.0: the 0.9 floor counts


def test_optimize_says_it_before_any_compute_and_takes_the_feet(notes):
    study_spec.validate(study_options.OptimizeOptions(friction=0.9, trials=8).spec())
    assert [line.split("):")[0] + ")" for line in _lines(notes)] == [PAPER_09]
    spec = study_options.OptimizeOptions(friction=0.9, foot_friction=0.9, trials=8).spec()
    assert spec.foot_friction == (0.9,) and study_spec.instances(spec)[0]["foot_friction"] == 0.9


def test_the_friction_tables_say_why_a_09_floor_equals_06_under_paper():
    from cpgjax.studies import registry
    from tests.study.test_spec_files import _fake_result

    paper = _fake_result(
        study_spec.StudySpec(
            "friction",
            num_trials=8,
            seeds=(0, 1, 2),
            friction=(0.3, 0.6, 0.9),
            group_by=("friction",),
            physics=("paper",),
        )
    )
    table = registry.report_friction(paper)
    assert "| friction | μ in effect |" in table
    assert [line.split("|")[1:3] for line in table.splitlines() if line.startswith("| 0.") and " − " not in line] == [
        [" 0.3 ", " 0.3 "],
        [" 0.6 ", " 0.6 "],
        [" 0.9 ", " 0.6 (the feet's) "],
    ]
    note = registry.notes(paper)
    assert "a floor above the feet's μ walks as the feet's (under physics paper, μ 0.9 walked as 0.6)" in note
    feet = _fake_result(
        study_spec.StudySpec(
            "friction",
            num_trials=8,
            seeds=(0, 1, 2),
            friction=(0.3, 0.6, 0.9),
            group_by=("friction",),
            physics=("paper",),
            foot_friction=(1.0,),
        )
    )
    assert "| 0.9 | 0.9 |" in registry.report_friction(feet)
    assert "Friction:" not in registry.notes(feet)
