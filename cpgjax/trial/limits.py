"""The allowed range of every physical input a user gives (command-line options, study definitions), each with the
reason for it, and the check that names the value, the range and the reason (docs/cli.md, "Inputs and their
ranges"). The command line turns each check into an option type; :func:`cpgjax.study.spec.validate` applies the same
ones to a study's grid, so a value means the same and is refused the same way in every command.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, NamedTuple

from cpgjax.go1.constants import TICK_S
from cpgjax.go1.model import MAX_ABS_SLOPE_DEG
from cpgjax.go1.terrain import BLOCK_DEPTH_M as BLOCK_DEPTH
from cpgjax.go1.terrain import MAX_AMPLITUDE_M


class Range(NamedTuple):
    """An interval of allowed values and why it is allowed."""

    low: float
    high: float
    reason: str
    low_open: bool = False
    high_open: bool = False

    def __str__(self) -> str:
        return f"{'(' if self.low_open else '['}{self.low:g}, {self.high:g}{')' if self.high_open else ']'}"

    def contains(self, value: float) -> bool:
        if not math.isfinite(value):
            return False
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return above and below

    def check(self, value: float, name: str | None = None) -> float:
        """``value`` if it is allowed.

        Raises:
          ValueError: "[<name> = ]<value> is outside the allowed range <range> (<reason>)".
        """
        value = float(value)
        if not self.contains(value):
            shown = f"{name} = {value!r}" if name else repr(value)
            raise ValueError(f"{shown} is outside the allowed range {self} ({self.reason})")
        return value


FRICTION = Range(
    0.1, 1.5, "Coulomb friction of the feet on the floor, from wet ice ≈ 0.1 to grippy rubber on dry concrete ≈ 1.5"
)
SLOPE_DEG = Range(
    -MAX_ABS_SLOPE_DEG, MAX_ABS_SLOPE_DEG, "uphill along +x; the model's gravity tilt", low_open=True, high_open=True
)
PAYLOAD_KG = Range(0.0, 20.0, "a load on the ~12 kg robot; the paper's heaviest is 15 kg")
TERRAIN_AMPLITUDE_M = Range(
    0.0, MAX_AMPLITUDE_M, "rough ground's peak-to-peak height; at most the smallest swing clearance g_c", low_open=True
)
BLOCK_DEPTH_M = Range(*BLOCK_DEPTH, "blocks' side: two cells of the height field (a top between the edges) to 4 m")
ROUGHNESS_M = Range(
    0.0,
    MAX_AMPLITUDE_M,
    "a study's rough ground: its peak-to-peak height, 0 the flat plane; at most the smallest swing clearance g_c",
)
TERRAIN_SEEDS = 2**32  # a rough ground's seeds: the integers 0 … 2³² − 1
TARGET_VELOCITY_MPS = Range(0.0, 2.0, "forward walking; the paper's targets are 0.3…0.8 m/s", low_open=True)
ROBOT_MASS_KG = Range(5.0, 40.0, "the Go1 weighs ~12 kg, with at most a 20 kg payload")
RUN_DURATION_S = Range(0.0, 3600.0, "a run of at most an hour", low_open=True)
TRANSITION_S = Range(0.0, 60.0, "each trial's parameter transition")
STEADY_S = Range(TICK_S, 600.0, "each trial's measured phase: at least one 1 ms tick")
MEASURE_S = Range(TICK_S, 600.0, "a measuring window: at least one 1 ms tick")
SETTLE_S = Range(0.0, 60.0, "holding the pose before measuring")
LIFT_M = Range(0.0, 1.0, "how high the simulated Go1 is hung up", low_open=True)
OBJECTIVE_FLOOR = Range(-20.0, -0.5, "J's lower bound and a fall's J, below every walking gait's J (1.5 … 2.3)")

MIN_TRIALS = 1
MAX_TRIALS = 1000
MAX_TRIALS_REASON = (
    "the GP keeps every trial, its work per trial grows with the cube of their number; the paper's runs have 40 to 100"
)
MAX_SEEDS = 10_000
MAX_SEEDS_REASON = (
    "seeds per group, each one more simulated robot in the batch; the paper's studies use 5, a "
    "cluster run of docs/scaling.md 250"
)
MIN_STUDY_TRIALS = 8
MIN_STUDY_TRIALS_REASON = (
    "a paper study changes its conditions at trials scaled to the run length and starts with "
    "random trials; below 8 a phase has no optimized trial"
)


def check_count(
    value: int,
    name: str | None = None,
    minimum: int = MIN_TRIALS,
    reason: str = "",
    maximum: int = MAX_TRIALS,
    maximum_reason: str = MAX_TRIALS_REASON,
) -> int:
    """An integer count in ``minimum`` … ``maximum``.

    Raises:
      ValueError: not an integer, or outside the range (the message gives the reason of the bound it passes).
    """
    shown = f"{name} = {value!r}" if name else repr(value)
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        why = f" ({reason})" if reason else ""
        raise ValueError(f"{shown}: need an integer >= {minimum}{why}")
    if value > maximum:
        raise ValueError(f"{shown}: need an integer <= {maximum} ({maximum_reason})")
    return value


def read_json(path, what: str) -> Any:
    """The JSON value in the file ``path``, a user's input file (``what`` names it in the message).

    Raises:
      ValueError: "<what> <path>: cannot read it (...)" or "<what> <path>: not valid JSON (...)".
    """
    try:
        return json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"{what} {path}: cannot read it ({err})") from None
    except json.JSONDecodeError as err:
        raise ValueError(f"{what} {path}: not valid JSON ({err})") from None
