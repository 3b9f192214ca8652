"""The paper's open readings as a study's switches (docs/decisions.md §1, §2, §7, §10): each reaches the controller,
the optimizer or the objective it names, a study without them is the study it was, and a bad one is refused in one
line before anything runs."""

import jax.numpy as jnp
import numpy as np
import pytest

from cpgjax import ablation, cli, cpg
from cpgjax.study import files as study_io
from cpgjax.study import spec as study_spec
from cpgjax.trial import params as param_space
from tests.test_cpg import _tilted_quat, observation

STUDY = """name = "switched"
trials = 2
seeds = 1
[grid]
payload_kg = [20.0]
physics = ["paper"]
[trial]
transition_s = 0.0
steady_s = 0.2
"""
SWITCHES = """[switches]
amplitude_form = "sqrt"
ucb_form = "botorch"
vmc_gate = "phase"
objective_floor = -5.0
"""


def _load(tmp_path, text):
    path = tmp_path / "study.toml"
    path.write_text(text)
    return study_spec.load(path)


def test_each_switch_reaches_what_it_names_and_unset_changes_nothing(tmp_path):
    plain, switched = _load(tmp_path, STUDY), _load(tmp_path, STUDY + SWITCHES)
    assert plain.switches is None and "switches" not in study_io.definition(plain)
    assert plain.cpg_config() == cpg.CPGConfig() and plain.optimizer_config().ucb_form == "paper"
    config = switched.cpg_config()
    assert config.amplitude_form == "sqrt" and config.vmc_contact_force_n == -np.inf
    assert config._replace(amplitude_form="paper", vmc_contact_force_n=10.0) == cpg.CPGConfig()
    assert switched.optimizer_config().ucb_form == "botorch"
    assert switched.switch_values().objective_floor == -5.0
    assert study_io.fingerprint(plain) != study_io.fingerprint(switched)


def test_the_phase_gate_gives_an_unloaded_stance_leg_its_virtual_force():
    """FL is in the CPG's stance phase with no load on its foot: the paper's reading (> 10 N) gives it no VMC torque,
    the phase-only reading does."""
    state = cpg.CPGState(
        jnp.full(4, 1.0), jnp.array([0.6, 3.9, 3.9, 0.6]), jnp.float32(0.0), jnp.float32(0.0), jnp.float32(0.0)
    )
    obs = observation(np.array([60.0, 0.0, 60.0, 60.0]), _tilted_quat(0.2, 0.15, 0.3))
    p = jnp.asarray(param_space.midpoint(), jnp.float32)
    taus = {}
    for gate in study_spec.VMC_GATES:
        config = study_spec.Switches(vmc_gate=gate).cpg_config(cpg.CPGConfig())
        _, _, diag = cpg.controller_step(config, state, p, cpg.controller_gates("vmc"), obs)
        taus[gate] = np.asarray(diag.tau_vmc_nm).reshape(4, 3)
    fl = 1
    assert np.all(taus["loaded"][fl] == 0.0) and np.abs(taus["phase"][fl]).max() > 1.0
    np.testing.assert_array_equal(taus["loaded"][2:], taus["phase"][2:])  # the loaded hind legs: the same


def test_a_fall_scores_the_moved_floor(tmp_path):
    """On 25° under 20 kg the Go1 falls from standing: with the floor at −5 a fallen trial's J is −5, not the paper's
    −1, and no trial's J is below it."""
    text = STUDY.replace("payload_kg = [20.0]", "payload_kg = [20.0]\nslope_deg = [25.0]").replace(
        "steady_s = 0.2", "steady_s = 2.0"
    )
    result = ablation.Engine(_load(tmp_path, text + "[switches]\nobjective_floor = -5.0\n"), backend="native").run()
    fell = np.asarray(result.trials.fell).ravel() > 0
    j = np.asarray(result.trials.objective).ravel()
    assert fell.any()
    np.testing.assert_array_equal(j[fell], -5.0)
    assert np.all(j >= -5.0)


@pytest.mark.parametrize(
    "line, message",
    [
        ('vmc_gate = "always"', "switches.vmc_gate: 'always' is not allowed; allowed: loaded, phase"),
        ("objective_floor = 1.0", "switches.objective_floor = 1.0 is outside the allowed range [-20, -0.5]"),
        ('ucb = "botorch"', "unknown key 'switches.ucb'; allowed in switches: amplitude_form, ucb_form"),
    ],
)
def test_a_bad_switch_is_refused_in_one_line(line, message, tmp_path, capsys, monkeypatch):
    path = tmp_path / "study.toml"
    path.write_text(STUDY + "[switches]\n" + line + "\n")
    monkeypatch.setattr(ablation, "Engine", lambda *a, **k: pytest.fail("an engine was built"))
    assert cli.main(["study", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err, err
