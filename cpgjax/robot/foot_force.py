"""The Go1's foot-force sensors in Newtons (docs/decisions.md §3): a stored calibration N = (raw − offset) · scale."""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

import numpy as np

from cpgjax.go1 import constants


class FootForceCalibration(NamedTuple):
    """N_i = (raw_i − offset_i) · scale_i: the Go1's foot sensor counts in Newtons (docs/decisions.md §3)."""

    offset_counts: np.ndarray  # (4,) raw value with the foot in the air
    newton_per_count: np.ndarray  # (4,)

    def to_newtons(self, raw_counts: np.ndarray) -> np.ndarray:
        return (raw_counts - self.offset_counts) * self.newton_per_count

    def save(self, path, **info) -> None:
        """JSON {offset_counts, newton_per_count, ...info} (``info``: how it was measured; :meth:`load` ignores it)."""
        Path(path).write_text(json.dumps({"offset_counts": self.offset_counts.tolist(),
                                          "newton_per_count": self.newton_per_count.tolist(), **info}, indent=1))

    @classmethod
    def load(cls, path) -> FootForceCalibration:
        d = json.loads(Path(path).read_text())
        return cls(np.asarray(d["offset_counts"], np.float64), np.asarray(d["newton_per_count"], np.float64))


def calibrate_foot_force(air_counts: np.ndarray, standing_counts: np.ndarray,
                         total_mass_kg: float) -> FootForceCalibration:
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
    return FootForceCalibration(offset, np.full(4, total_mass_kg * constants.GRAVITY_MPS2 / loaded))
