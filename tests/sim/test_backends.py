"""The backend interface (``cpgjax.sim.base.Backend``), checked once on both backends: its members and their
signatures, bad parameters, a failing instance and a fall. Both use the session batches of ``conftest`` (each backend
compiled once per test session)."""

import inspect

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cpgjax.go1 import model as go1_model
from cpgjax.sim import base
from cpgjax.trial import objective, protocol

BACKEND_FIXTURES = {"mjx": "short_sim", "native": "native_sim"}


@pytest.fixture(params=sorted(BACKEND_FIXTURES))
def sim(request) -> base.Backend:
    return request.getfixturevalue(BACKEND_FIXTURES[request.param])


def _joints(sim, state) -> tuple[np.ndarray, np.ndarray]:
    """(qpos, qvel) of every instance in a backend's state."""
    if sim.name == "mjx":
        return np.asarray(state.data.qpos), np.asarray(state.data.qvel)
    layout = sim.physics.layout
    return state.physics[:, layout.qpos], state.physics[:, layout.qvel]


def _with_joints(sim, state, qpos, qvel):
    """``state`` with the instances' qpos and qvel replaced."""
    if sim.name == "mjx":
        data = state.data
        return state._replace(
            data=data.replace(qpos=jnp.asarray(qpos, data.qpos.dtype), qvel=jnp.asarray(qvel, data.qvel.dtype))
        )
    layout, physics = sim.physics.layout, state.physics.copy()
    physics[:, layout.qpos], physics[:, layout.qvel] = qpos, qvel
    return state._replace(physics=physics)


def _members(kind) -> dict[str, object]:
    return {name: value for name, value in vars(kind).items() if not name.startswith("_")}


def test_both_backends_have_every_member_of_the_interface_with_its_signature(sim):
    assert isinstance(sim, base.Backend)
    assert sim.name in BACKEND_FIXTURES and sim.batch_size == sim.scenario.batch_size
    for name in base.Backend.__annotations__:
        assert hasattr(sim, name), name
    assert base.Backend.__abstractmethods__ == {"batch_size", "reset", "trial", "rollout", "with_scenario"}
    for name, member in _members(base.Backend).items():
        if callable(member):
            ours, interface = inspect.signature(getattr(type(sim), name)), inspect.signature(member)
            assert [(p.name, p.kind, p.default) for p in ours.parameters.values()] == [
                (p.name, p.kind, p.default) for p in interface.parameters.values()
            ], name


def test_bad_parameters_are_rejected_before_simulation(sim, mid_params):
    bad = mid_params.copy()
    bad[2, 4] = 2.5
    with pytest.raises(ValueError, match=r"amplitude_mu = 2.5 \(instance 2\)"):
        sim.reset(bad)
    with pytest.raises(ValueError, match="expected shape"):
        sim.reset(mid_params[:2])


def test_one_exploding_instance_leaves_the_others_unchanged(sim, mid_params, vmc_tegotae_gates, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # C MuJoCo logs its instability warning to ./MUJOCO_LOG.TXT
    start = sim.reset(mid_params)
    start, _ = sim.trial(start, mid_params, vmc_tegotae_gates)
    clean_start = jax.tree.map(lambda x: x.copy(), start)  # a trial consumes its state
    qpos, qvel = _joints(sim, start)
    qvel = qvel.copy()
    qvel[2] = np.inf
    _, clean = sim.trial(clean_start, mid_params, vmc_tegotae_gates)
    end, broken = sim.trial(_with_joints(sim, start, qpos, qvel), mid_params, vmc_tegotae_gates)
    assert float(broken.failed[2]) == 1.0 and float(clean.failed[2]) == 0.0
    assert float(broken.safety_margin[2]) == protocol.FAILED_MARGIN and float(clean.safety_margin[2]) > 0.0
    assert float(objective.objective(jax.tree.map(lambda x: x[2], broken), 0.5)) == objective.MIN_OBJECTIVE
    assert all(np.all(np.isfinite(a)) for a in _joints(sim, end))
    others = np.arange(sim.batch_size) != 2
    for a, b in zip(jax.tree.leaves(clean), jax.tree.leaves(broken), strict=True):
        np.testing.assert_array_equal(np.asarray(a)[others], np.asarray(b)[others])


def test_a_fall_is_detected_and_the_robot_stands_up_again(sim, mid_params, vmc_tegotae_gates):
    start = sim.reset(mid_params)
    qpos, qvel = _joints(sim, start)
    qpos = qpos.copy()
    qpos[0, 3:7] = [0.0, 1.0, 0.0, 0.0]  # instance 0 on its back
    end, record = sim.trial(_with_joints(sim, start, qpos, qvel), mid_params, vmc_tegotae_gates)
    assert float(record.fell[0]) == 1.0 and float(record.fell[5]) == 0.0
    assert float(record.safety_margin[0]) < 0.0 < float(record.safety_margin[5]) <= 1.0
    np.testing.assert_allclose(_joints(sim, end)[0][0], go1_model.standing_qpos(), atol=1e-6)
