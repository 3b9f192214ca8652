"""A study's instances as one padded batch: each instance's conditions, gates, seed, physics profile, feet, ground,
data reuse and active parameters, laid out along the placement's padded batch (``study.placement``), and the
scenarios they make (:meth:`InstanceBatch.scenario_at`). The engine (``cpgjax.ablation``) runs its trials on them."""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import numpy as np

from cpgjax import cpg
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import terrain as terrains
from cpgjax.study import spec as study_spec
from cpgjax.study.placement import Placement
from cpgjax.study.spec import Conditions
from cpgjax.trial import params as param_space
from cpgjax.trial import protocol


class InstanceBatch(NamedTuple):
    """Every instance's arrays along the padded batch (padded B: the placement's copies of the last instance fill
    it)."""

    padded: Conditions  # the planned conditions, each (padded B, num_trials)
    gates: cpg.Gates  # each (padded B, ...)
    local_gates: cpg.Gates  # the rows of this process's devices (``Placement.rows``)
    seeds: np.ndarray  # (padded B,) int
    physics: np.ndarray  # (padded B,) str, the physics profile
    feet: np.ndarray  # (padded B,) float64, the foot friction
    reuse: np.ndarray  # (padded B,) bool, data reuse at a target change
    grounds: dict[str, np.ndarray]  # the ground's fields (``terrains.ground_fields``), each (padded B,)
    active: np.ndarray  # (padded B, 8) bool, the parameters the optimizer searches
    uses_records: bool  # some target changes: the optimizer observes trial records, not J

    def scenario(self, trial: int, conditions: Conditions | None = None) -> go1_model.Scenario:
        """Every instance's scenario of trial ``trial`` (padded batch), under ``conditions`` as :meth:`scenario_at`.

        Args:
          trial: the trial, 0 … ``num_trials`` − 1.
          conditions: the padded batch's conditions, each (padded B, num_trials) (default: :attr:`padded`).

        Returns:
          The padded batch's scenarios, each field (padded B,).
        """
        return self.scenario_at(trial, slice(None), conditions)

    def scenario_at(self, trials, instances, conditions: Conditions | None = None) -> go1_model.Scenario:
        """The scenarios of (trial, instance) pairs (NumPy indices into the padded conditions, broadcast together):
        one batch of them, e.g. the trials a study's analysis walks again. ``conditions``: the padded batch's (default
        the planned ones, :attr:`padded`; the engine's trials take them walked, ``study_spec.walked``).

        Args:
          trials: trial indices (an integer or an integer array).
          instances: row indices of the padded batch (an integer, an integer array or a slice), broadcast with
            ``trials`` to one dimension.
          conditions: the padded batch's conditions, each (padded B, num_trials) (default: :attr:`padded`).

        Returns:
          One scenario per (trial, instance) pair, each field (pairs,).
        """
        c = self.padded if conditions is None else conditions
        return go1_model.make_scenarios(
            c.friction[instances, trials],
            c.slope_deg[instances, trials],
            c.payload_kg[instances, trials],
            self.physics[instances],
            c.mass_scale[instances, trials],
            c.latency_ticks[instances, trials],
            c.noise_scale[instances, trials],
            self.seeds[instances],  # noise per seed
            foot_friction=self.feet[instances],
            **{f: v[instances] for f, v in self.grounds.items()},
        )


def instance_batch(labels: list[dict[str, Any]], conditions: Conditions, placement: Placement) -> InstanceBatch:
    """The instances of a study as one padded batch.

    Args:
      labels: each instance's labels (``study_spec.instances``), B of them.
      conditions: the study's planned conditions (``study_spec.conditions``), each (B, num_trials).
      placement: the batch's placement (``study.placement.make_placement``), which pads it.

    Returns:
      The :class:`InstanceBatch` along the placement's padded batch.
    """
    pad = placement.pad
    padded = Conditions(*(pad(c) for c in conditions))
    controllers = pad(np.array([lab["controller"] for lab in labels]))
    gaits = pad(np.array([lab["gait"] for lab in labels]))
    gates = protocol.batch_gates(controllers.tolist(), gaits.tolist())
    first, stop = placement.rows
    grounds = terrains.ground_fields(map(study_spec.ground, labels))
    targets = padded.target_velocity_mps
    return InstanceBatch(
        padded=padded,
        gates=gates,
        local_gates=jax.tree.map(lambda g: g[first:stop], gates),
        seeds=pad(np.array([lab["seed"] for lab in labels])),
        physics=pad(np.array([lab["physics"] for lab in labels])),
        feet=pad(np.array([lab["foot_friction"] for lab in labels], np.float64)),
        reuse=pad(np.array([lab["data_reuse"] for lab in labels])),
        grounds={field: pad(values) for field, values in grounds.items()},
        active=param_space.active_parameters(gates.tegotae > 0),
        uses_records=bool(np.any(targets[:, 1:] != targets[:, :-1])),
    )
