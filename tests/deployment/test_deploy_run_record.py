"""run.json's ``ran`` (``deploy.what_ran``) of an online optimization on the real Go1, from the options ``cpgjax
deploy`` parsed (no robot: ``deploy.run`` is replaced; a replay of a parameter file on the simulated Go1 is checked
end to end in tests/deployment/test_tick_log.py)."""

from cpgjax import cli
from cpgjax.deployment import deploy

FIRST = {
    "ground_clearance_m": 0.07,
    "ground_penetration_m": 0.008,
    "omega_swing_rad_s": 17.0,
    "omega_stance_rad_s": 14.0,
    "amplitude_mu": 1.0,
    "x_offset_front_m": -0.05,
    "x_offset_hind_m": -0.02,
    "sigma_n": 0.1,
}
SECOND = {
    "ground_clearance_m": 0.09,
    "ground_penetration_m": 0.014,
    "omega_swing_rad_s": 22.0,
    "omega_stance_rad_s": 11.0,
    "amplitude_mu": 1.6,
    "x_offset_front_m": -0.02,
    "x_offset_hind_m": -0.05,
    "sigma_n": 0.25,
}


def test_an_optimization_on_the_go1_records_its_options_and_each_trials_parameters(tmp_path, monkeypatch):
    """On the Go1 the physics is the robot's and friction and slope are unknown (null) while the payload counts;
    trial 0 is the optimizer's first proposal (no first parameters, no file); each trial's parameters are its
    row's."""
    ran = []
    monkeypatch.setattr(deploy, "run", lambda args: ran.append(args) or 0)
    calibration = tmp_path / "calibration.json"
    deploy.sim_calibration().save(calibration)
    assert (
        cli.main(
            [
                "deploy",
                "--robot",
                "go1",
                "--calibration",
                str(calibration),
                "--optimize",
                "--controller",
                "vmc",
                "--payload-kg",
                "2",
                "--target-velocity-mps",
                "0.7",
                "--trials",
                "3",
                "--transition-s",
                "0.5",
                "--steady-s",
                "2",
                "--optimizer",
                "random",
                "--seed",
                "7",
                "--log-dir",
                str(tmp_path / "run"),
            ]
        )
        == 0
    )
    rows = [{"trial": 0, **FIRST, "objective": 0.4}, {"trial": 1, **SECOND, "objective": 0.9}]
    assert deploy.what_ran(ran[-1], rows) == {
        "mode": "optimize",
        "robot": "go1",
        "controller": "vmc",
        "gait": "trot",
        "physics": "robot",
        "startup": "paper",
        "friction": None,
        "slope_deg": None,
        "payload_kg": 2.0,
        "target_velocity_mps": 0.7,
        "transition_s": 0.5,
        "steady_s": 2.0,
        "duration_s": None,
        "num_trials": 3,
        "optimizer": "random",
        "seed": 7,
        "params_file": None,
        "params": None,
        "trial_params": [{"trial": 0, **FIRST}, {"trial": 1, **SECOND}],
    }
