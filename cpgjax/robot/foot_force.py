"""The Go1's foot-force sensors in Newtons (docs/decisions.md §3): a stored calibration N = (raw − offset) · scale."""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

import numpy as np

from cpgjax.go1 import constants
from cpgjax.trial import limits

# A plausible newton-per-count scale: three decades around the simulated sensor's 0.5 N/count. Outside it a reading
# of the int16 sensor would be a sub-gram or a many-tonne force, and the loop's load context and foot-force
# feedback would be meaningless.
N_PER_COUNT_RANGE = (1e-3, 10.0)
COUNT_RANGE = (-32768, 32767)  # the sensor's int16 counts
NUM_FEET = 4


class FootForceCalibration(NamedTuple):
    """N_i = (raw_i − offset_i) · scale_i: the Go1's foot sensor counts in Newtons (docs/decisions.md §3)."""

    offset_counts: np.ndarray  # (4,) raw value with the foot in the air
    newton_per_count: np.ndarray  # (4,)

    def to_newtons(self, raw_counts: np.ndarray) -> np.ndarray:
        return (raw_counts - self.offset_counts) * self.newton_per_count

    def save(self, path, **info) -> None:
        """JSON {offset_counts, newton_per_count, ...info} (``info``: how it was measured; :meth:`load` ignores it)."""
        Path(path).write_text(
            json.dumps(
                {
                    "offset_counts": self.offset_counts.tolist(),
                    "newton_per_count": self.newton_per_count.tolist(),
                    **info,
                },
                indent=1,
            )
        )

    @classmethod
    def load(cls, path) -> FootForceCalibration:
        """The calibration in a :meth:`save` file, checked by :func:`check_calibration`.

        Raises:
          ValueError: unreadable or invalid JSON, a missing key, or values :func:`check_calibration` refuses; the
            message names the file and the key.
        """
        d = limits.read_json(path, "calibration")
        if not isinstance(d, dict):
            raise ValueError(f"calibration {path}: expected a JSON object with offset_counts and newton_per_count")
        values = {}
        for key in cls._fields:
            if key not in d:
                raise ValueError(f"calibration {path}: missing key {key!r}")
            try:
                values[key] = np.asarray(d[key], np.float64)
            except (TypeError, ValueError):
                raise ValueError(f"calibration {path}: {key} = {d[key]!r} is not a list of numbers") from None
        return check_calibration(cls(**values), what=f"calibration {path}")


def check_calibration(cal: FootForceCalibration, what: str = "calibration") -> FootForceCalibration:
    """``cal`` if it has exactly 4 finite offsets within the int16 counts and 4 finite scales in
    :data:`N_PER_COUNT_RANGE`.

    Raises:
      ValueError: the message names the field, the foot, the value and the allowed range.
    """
    for key, (lo, hi), unit in (
        ("offset_counts", COUNT_RANGE, "counts"),
        ("newton_per_count", N_PER_COUNT_RANGE, "N/count"),
    ):
        values = np.asarray(getattr(cal, key), np.float64)
        if values.shape != (NUM_FEET,):
            raise ValueError(f"{what}: {key} needs exactly {NUM_FEET} values (FR, FL, RR, RL), got {values.tolist()}")
        bad = ~(np.isfinite(values) & (values >= lo) & (values <= hi))
        if bad.any():
            foot = int(np.argmax(bad))
            raise ValueError(
                f"{what}: {key}[{foot}] = {float(values[foot])!r} is outside the allowed range [{lo:g}, {hi:g}] {unit}"
            )
    return cal


def calibrate_foot_force(
    air_counts: np.ndarray, standing_counts: np.ndarray, total_mass_kg: float
) -> FootForceCalibration:
    """Calibration from raw samples: the offset is each foot's median with the robot lifted, feet in the air
    (``air_counts`` (K, 4); the median, not the minimum, so the sensor's noise does not bias it); one common scale
    makes the four feet carry the robot's weight while standing still (``standing_counts`` (M, 4)).

    Raises:
      ValueError: the standing signal is not above the offsets (no load seen).
    """
    offset = np.median(np.asarray(air_counts, np.float64), axis=0)
    loaded = np.sum(np.mean(np.asarray(standing_counts, np.float64), axis=0) - offset)
    if not loaded > 0:
        raise ValueError(f"standing foot counts are not above the in-air offsets {offset}; cannot calibrate")
    return check_calibration(
        FootForceCalibration(offset, np.full(4, total_mass_kg * constants.GRAVITY_MPS2 / loaded)),
        what="measured calibration",
    )
