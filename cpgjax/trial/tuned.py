"""``best_params.json``: CPG parameters and what they were tuned for.

Written by ``cpgjax optimize``, ``cpgjax deploy --optimize`` and every study (one file per group), read back by
``cpgjax deploy --params`` and ``cpgjax walk --params``. Besides the 8 parameters (``params``, by name) a file
records the run it came from (:data:`TUNED_FOR`): the controller, its gait (``cpg.GAITS``), the physics profile, the
scenario (friction, slope, payload) and the target velocity. A replay uses those unless an option overrides one. A
null value means the run did not know it (a real robot's floor has no simulated friction or slope, and no physics
profile); the replay then keeps its own option. A file without a gait walked the trot (it was written before gaits
were a choice). A plain JSON list of 8 numbers is read as parameters with nothing recorded.
"""

from __future__ import annotations

import json
import shlex
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from cpgjax import cpg, outputs
from cpgjax.go1 import physics as physics_profiles
from cpgjax.trial import limits
from cpgjax.trial import params as param_space

FILE_NAME = "best_params.json"
OUTPUTS = (
    outputs.OutputFile(
        FILE_NAME,
        "the best trial's parameters and what they were tuned for (deploy / walk --params)",
        outputs.check_json,
    ),
)

# What a run was tuned for, in the order a replay names them; the numeric ones with their allowed ranges.
TUNED_FOR = ("controller", "gait", "physics", "friction", "slope_deg", "payload_kg", "target_velocity_mps")
RANGES = {
    "friction": limits.FRICTION,
    "slope_deg": limits.SLOPE_DEG,
    "payload_kg": limits.PAYLOAD_KG,
    "target_velocity_mps": limits.TARGET_VELOCITY_MPS,
}
NAMES = {"controller": cpg.CONTROLLERS, "gait": tuple(cpg.GAITS), "physics": tuple(physics_profiles.PROFILES)}


class ParamsFile(NamedTuple):
    """A read parameter file."""

    params: np.ndarray  # (8,), physical units, in the paper's box
    tuned_for: dict[str, Any]  # the :data:`TUNED_FOR` fields the file records (non-null), checked
    path: str


def save(path, params: np.ndarray, tuned_for: dict[str, Any], **info) -> None:
    """Write ``params`` with every :data:`TUNED_FOR` field of ``tuned_for`` (None: not known) and ``info``
    (objective, trial, ...).

    Raises:
      KeyError: ``tuned_for`` lacks a field (every file states all of them, null where unknown).
    """
    recorded = {name: tuned_for[name] for name in TUNED_FOR}
    Path(path).write_text(json.dumps({"params": param_space.as_dict(params), **recorded, **info}, indent=1))


def _checked(path, data: dict) -> dict[str, Any]:
    tuned = {}
    for name in TUNED_FOR:
        value = data.get(name, cpg.DEFAULT_GAIT if name == "gait" else None)
        if value is None:
            continue
        if name in NAMES:
            if value not in NAMES[name]:
                raise ValueError(f"parameter file {path}: {name} {value!r} is not one of {', '.join(NAMES[name])}")
        elif isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"parameter file {path}: {name} {value!r} is not a number")
        else:
            try:
                value = RANGES[name].check(value, name)
            except ValueError as err:
                raise ValueError(f"parameter file {path}: {err}") from None
        tuned[name] = value
    return tuned


def load(path) -> ParamsFile:
    """The parameters (validated) and what they were tuned for, from a :func:`save` file or a JSON list of 8 numbers.

    Raises:
      ValueError: unreadable or invalid JSON, a missing key, a value outside the paper's box, or a recorded field
        that is not allowed; the message names the file and the key.
    """
    data = limits.read_json(path, "parameter file")
    tuned: dict[str, Any] = {}
    if isinstance(data, dict):
        if not isinstance(data.get("params"), dict):
            raise ValueError(f"parameter file {path}: missing key 'params' (an object of {param_space.PARAM_NAMES})")
        missing = [name for name in param_space.PARAM_NAMES if name not in data["params"]]
        if missing:
            raise ValueError(f"parameter file {path}: missing key 'params.{missing[0]}'")
        tuned = _checked(path, data)
        data = [data["params"][name] for name in param_space.PARAM_NAMES]
    try:
        values = np.asarray(data, np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"parameter file {path}: expected {param_space.NUM_PARAMS} numbers") from None
    return ParamsFile(param_space.validate(values, what=f"parameter file {path}"), tuned, str(path))


def describe(tuned_for: dict[str, Any]) -> str:
    """'controller tegotae, gait trot, physics paper, friction 0.6, slope 0°, payload 0 kg, v* 0.5 m/s' (the
    recorded ones)."""
    shown = {
        "controller": "controller {}",
        "gait": "gait {}",
        "physics": "physics {}",
        "friction": "friction {:g}",
        "slope_deg": "slope {:g}°",
        "payload_kg": "payload {:g} kg",
        "target_velocity_mps": "v* {:g} m/s",
    }
    return ", ".join(shown[name].format(tuned_for[name]) for name in TUNED_FOR if name in tuned_for) or "nothing"


def replay_hint(params_path) -> str:
    """The commands that replay a ``best_params.json`` as it was tuned (the file carries the controller, the physics
    profile, the scenario and the target, which both commands use)."""
    return (
        f"replay the best: cpgjax deploy --robot sim --params {shlex.quote(str(params_path))}; "
        f"check it in simulation: cpgjax walk --params {shlex.quote(str(params_path))}"
    )
