"""``cpgjax deploy calibrate``: measure the Go1's foot-force sensors and save their calibration (docs/decisions.md §3).

The Go1 reports each foot's force as a raw int16 with an offset and no unit. The calibration is measured in two
stands of the 1 kHz loop (:func:`hardware_io.stand`: soft start, hold the standing pose, damp; every safety check
on): first with the robot hung up so that its feet are in the air (each foot's minimum is its offset), then standing
on the ground (one scale makes the four feet carry the robot's weight), fitted by
:func:`foot_force.calibrate_foot_force` and saved as JSON with how it was measured; ``cpgjax deploy --calibration
FILE`` loads it and the loop converts every reading to Newtons with it.

On the robot an operator hangs it up and puts it down when asked; the simulated Go1 (``--robot sim``) is lifted
and put down through its control port. Each stand keeps a per-tick log next to the calibration file
(:func:`tick_log_paths`: ``<name>.air.ticks.arrows``, ``<name>.standing.ticks.arrows``), as a deploy run does.
"""

from __future__ import annotations

import contextlib
import logging
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np

from cpgjax import hardware_io as hio
from cpgjax import outputs
from cpgjax.deployment import deploy, tick_log
from cpgjax.deployment.options import CalibrateOptions
from cpgjax.robot import foot_force
from cpgjax.robot import safety as go1_safety
from cpgjax.robot import transport as go1_transport

log = logging.getLogger(__name__)


class CalibrationError(RuntimeError):
    """A measuring stand did not complete (safety trip) or saw no robot state."""


class Measurement(NamedTuple):
    calibration: foot_force.FootForceCalibration
    air_counts: np.ndarray  # (K, 4) raw counts, feet in the air
    standing_counts: np.ndarray  # (M, 4) raw counts, standing still


STANDS = ("air", "standing")
# Each stand's per-tick log, NAME.<stand>.ticks.arrows beside the calibration file NAME.json (tick_log_paths).
STAND_LOGS = {
    stand: outputs.OutputFile(
        f"NAME.{stand}.{tick_log.FILE_NAME}",
        "the per-tick log of a calibration stand",
        tick_log.check_tick_log,
        pattern=rf".+\.{stand}\.{re.escape(tick_log.FILE_NAME)}",
    )
    for stand in STANDS
}
OUTPUTS = tuple(STAND_LOGS.values())


def tick_log_paths(out: Path) -> dict[str, Path]:
    """The per-tick log of each measuring stand, next to the calibration file ``out``."""
    out = Path(out)
    return {stand: out.with_name(f"{out.stem}.{stand}.{tick_log.FILE_NAME}") for stand in STANDS}


def calibration_file(stand_log: Path) -> Path:
    """The calibration file beside which ``stand_log`` (one of :func:`tick_log_paths`) lies."""
    stand_log = Path(stand_log)
    stand = next(s for s, entry in STAND_LOGS.items() if entry.matches(stand_log.name))
    return stand_log.with_name(stand_log.name.removesuffix(f".{stand}.{tick_log.FILE_NAME}") + ".json")


def measure_counts(
    transport: go1_transport.Transport,
    measure_s: float,
    settle_s: float,
    loop: hio.LoopConfig,
    safety: go1_safety.SafetyConfig,
    tick_log_path: Path | None = None,
) -> np.ndarray:
    """Raw foot counts (K, 4) of the robot states received while the loop holds the standing pose, after the first
    ``settle_s`` of holding it. ``tick_log_path``: where the stand's per-tick log goes (None: not kept).

    Raises:
      CalibrationError: the stand ended with a safety trip, or no state arrived in the measuring window.
    """
    writer = contextlib.nullcontext() if tick_log_path is None else deploy.tick_log_writer(tick_log_path, loop)
    with writer as sink:
        result = hio.stand(transport, settle_s + measure_s, loop, safety, sink)
    if result.trip is not None:
        kept = "" if tick_log_path is None else f" (per-tick log {tick_log_path})"
        raise CalibrationError(f"the measuring stand stopped: {result.trip}{kept}")
    ticks = result.log
    window = np.flatnonzero(ticks.phase == hio.STAND)[round(settle_s / loop.period_s) :]
    counts = ticks.foot_force_raw[window[ticks.fresh[window]]]
    if counts.shape[0] == 0:
        raise CalibrationError("no robot state arrived while measuring")
    return counts.astype(np.int64)


def measure(
    transport: go1_transport.Transport,
    total_mass_kg: float,
    lifted: Callable[[bool], None],
    air_s: float = 2.0,
    stand_s: float = 3.0,
    settle_s: float = 1.0,
    loop: hio.LoopConfig = hio.LoopConfig(),
    safety: go1_safety.SafetyConfig = go1_safety.SafetyConfig(),
    tick_logs: dict[str, Path] | None = None,
) -> Measurement:
    """The two measuring stands and the fit. ``lifted(True)`` must leave the robot hung up with its feet in the air,
    ``lifted(False)`` put it down on the ground (it stands up in the second stand). ``tick_logs``: each stand's
    per-tick log path (:func:`tick_log_paths`; None: not kept)."""
    logs = tick_logs or {}
    lifted(True)
    air = measure_counts(transport, air_s, settle_s, loop, safety, logs.get("air"))
    lifted(False)
    standing = measure_counts(transport, stand_s, settle_s, loop, safety, logs.get("standing"))
    return Measurement(foot_force.calibrate_foot_force(air, standing, total_mass_kg), air, standing)


def _ask_operator(hung_up: bool) -> None:
    input(
        "Hang the robot up so that its four feet are in the air, then press Enter: "
        if hung_up
        else "Put the robot down on the ground (lying or on its feet), then press Enter; it will stand up: "
    )


def _sim_lifter(server, lift_m: float) -> Callable[[bool], None]:
    """``lifted`` for the simulated Go1: hang it up ``lift_m`` [m] high, or put it down (reset) on the ground."""
    return lambda hung_up: server.lift(lift_m) if hung_up else server.reset()


def run(options: CalibrateOptions) -> int:
    """``cpgjax deploy calibrate`` with its checked options (``out`` and its stands' per-tick logs files it may
    write). Returns 0 when the calibration is saved, 2 when a measuring stand failed."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    loop, safety = deploy.loop_and_safety(options)
    mass_kg = options.mass_kg if options.mass_kg is not None else deploy.robot_mass_kg(options.payload_kg)
    tick_logs = tick_log_paths(options.out)
    with deploy.connect(options) as (transport, server):
        lifted = _ask_operator if server is None else _sim_lifter(server, options.lift_m)
        try:
            m = measure(
                transport, mass_kg, lifted, options.air_s, options.stand_s, options.settle_s, loop, safety, tick_logs
            )
        except (CalibrationError, ValueError) as e:
            print(f"cpgjax deploy calibrate: {e}", file=sys.stderr)
            return 2
    standing_n = m.calibration.to_newtons(np.mean(m.standing_counts, axis=0))
    m.calibration.save(
        options.out,
        robot=options.robot,
        total_mass_kg=mass_kg,
        air_samples=len(m.air_counts),
        standing_samples=len(m.standing_counts),
        air_counts_max=np.max(m.air_counts, axis=0).tolist(),
        standing_counts_mean=np.mean(m.standing_counts, axis=0).round(2).tolist(),
        standing_n=standing_n.round(2).tolist(),
    )
    print(
        f"offsets {m.calibration.offset_counts} counts, {m.calibration.newton_per_count[0]:.4f} N/count; "
        f"standing: {standing_n.round(1)} N per foot (sum {standing_n.sum():.1f} N = {mass_kg:.2f} kg · g); "
        f"saved {options.out} (per-tick logs: {', '.join(str(p) for p in tick_logs.values())})"
    )
    return 0
