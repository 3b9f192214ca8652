"""The condition one walk runs in: the floor, the ground, the load, the target velocity and the gait.

One scalar :class:`Condition` per walk, the fields that the walk's records (``sim.walk``), a study's gaits and videos
(``studies.video``) and a recording's rollouts (``study.scene``) carry; a study's batch holds the same conditions as
per-instance arrays (``study.spec.Conditions``, ``go1.model.Scenario``). Records embed it as their ``condition``; the
files they write keep its fields flat, as columns and keys of their own.
"""

from __future__ import annotations

from typing import NamedTuple

from cpgjax import cpg
from cpgjax.go1 import terrain as terrains


class Condition(NamedTuple):
    """One walk's condition; the defaults are ``go1_model.make_scenarios``'s and the paper's v* (0.5 m/s)."""

    friction: float = 0.6  # the floor's μ asked for
    slope_deg: float = 0.0  # uphill along +x (docs/decisions.md §4)
    payload_kg: float = 0.0  # mass added on the trunk (docs/decisions.md §6)
    target_velocity_mps: float = 0.5  # v* of the objective
    gait: str = cpg.DEFAULT_GAIT  # the CPG's coupling pattern (cpg.GAITS)
    foot_friction: float = -1.0  # the feet's μ asked for (go1_model.Scenario.foot_friction; −1: the profile's own)
    ground: terrains.Ground = terrains.FLAT_GROUND
