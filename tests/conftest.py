"""Session-wide compiled simulators, shared by the tests so each batch shape compiles once per test process (once in
each pytest-xdist worker under `make test`)."""

import numpy as np
import pytest

from cpgjax import mjx_go1
from cpgjax.go1 import model as go1_model
from cpgjax.sim import native as native_go1
from cpgjax.trial import params as param_space
from cpgjax.trial import protocol

# Short trials keep the suite fast; the trial logic is identical to the paper's 1.5 s + 3 s.
SHORT_TRIAL = protocol.TrialConfig(transition_steps=400, steady_steps=1200)
# One batch covering the scenario checks: nominal, heavy, uphill, slippery, coarse, nominal; under MuJoCo's soft
# contact, whose friction rule (the floor's μ) keeps the coarse floor coarse.
SCENARIOS = dict(
    friction=[0.6, 0.6, 0.6, 0.1, 0.9, 0.6],
    slope_deg=[0, 0, 6, 0, 0, 0],
    payload_kg=[0, 15, 0, 0, 0, 0],
    physics="soft",
)


@pytest.fixture(scope="session")
def short_sim():
    """The session batch on the MJX backend."""
    return mjx_go1.MJXBackend(go1_model.make_scenarios(**SCENARIOS), trial_config=SHORT_TRIAL)


@pytest.fixture(scope="session")
def native_sim():
    """The session batch on the native backend (C MuJoCo)."""
    return native_go1.NativeBackend(go1_model.make_scenarios(**SCENARIOS), trial_config=SHORT_TRIAL)


@pytest.fixture(scope="session")
def mid_params():
    return np.tile(param_space.midpoint(), (len(SCENARIOS["friction"]), 1))


@pytest.fixture(scope="session")
def vmc_tegotae_gates():
    return protocol.batch_gates(["vmc_tegotae"] * len(SCENARIOS["friction"]))


@pytest.fixture(scope="session")
def two_trials(short_sim, mid_params, vmc_tegotae_gates):
    """Records of the second of two back-to-back short trials for the session batch (first trial = warm-up)."""
    state = short_sim.reset(mid_params)
    state, _ = short_sim.trial(state, mid_params, vmc_tegotae_gates)
    state, record = short_sim.trial(state, mid_params, vmc_tegotae_gates)
    return state, record
