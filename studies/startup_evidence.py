"""Where a restart from standing on a slope goes wrong, and which start-up fixes it (docs/decisions.md §18): the
gaits that walked a slope in a finished slope study, each restarted from standing on that slope under one change of
the start at a time.

    python studies/startup_evidence.py results/slope_adaptation [--backend native|mjx] [--variants paper,ramp_lean]

Two sets of gaits per slope, from the folder's ``trials.parquet`` (optimized trials, the slopes > 0):

* ``after a fall``: the instance's last gait that walked the slope before a fall (the restarts the study could not
  avoid, as ``studies/fall_chains.py --rewalk`` picks them), each gait once;
* ``walked``: every distinct gait that walked the slope.

Each gait then runs one trial (1.5 s transition + 3 s, the study's timing and physics) from standing on its slope,
the transition from the gait itself (no blend) unless a variant says otherwise; it "starts" if the trial does not
fall. The table gives, per variant, set and slope, the starts out of the gaits with the Clopper–Pearson 95 %
interval, and Fisher's exact p against the paper's start.
"""

from __future__ import annotations

import argparse
import pathlib
from typing import NamedTuple

import numpy as np

from cpgjax import ablation, cpg
from cpgjax.go1 import model as go1_model
from cpgjax.sim import backends
from cpgjax.studies import stats
from cpgjax.study import files as study_io
from cpgjax.trial import params as param_space
from cpgjax.trial import protocol

PAPER = cpg.CPGConfig()


class Variant(NamedTuple):
    """One change of the start against the paper's."""

    name: str
    change: str  # what changes, for the table
    config: cpg.CPGConfig = PAPER
    blend_from_midpoint: bool = False  # the transition starts from the box midpoint, not from the gait itself


VARIANTS = (
    Variant("paper", "the paper's start: r = 0.1 → μ at α = 50, trot phases, feet under the hips, VMC at once"),
    Variant("blend", "the 1.5 s blend starts from the box midpoint (as after a fall, from another gait)",
            blend_from_midpoint=True),
    Variant("ramp", "amplitude target ramps 0 → μ over 1.5 s", PAPER._replace(start_ramp_s=1.5)),
    Variant("ramp_3s", "amplitude target ramps 0 → μ over 3 s", PAPER._replace(start_ramp_s=3.0)),
    Variant("phase", "initial phases + π/2 (the first pair starts mid-swing)",
            PAPER._replace(start_phase_rad=float(np.pi / 2))),
    Variant("lean", "standing posture leans into the slope: feet at h·tan(pitch) in x",
            PAPER._replace(start_lean=True)),
    Variant("vmc_delay", "VMC off for the first 1.5 s", PAPER._replace(start_vmc_delay_s=1.5)),
    Variant("kp", "K_p 70 → 100 N·m/rad (everywhere)", PAPER._replace(kp_nm_rad=100.0)),
    Variant("ramp_lean", "lean, blended out over a 1.5 s amplitude ramp",
            PAPER._replace(start_ramp_s=1.5, start_lean=True)),
    Variant("ramp_lean_phase", "lean blended out over a 1.5 s ramp, initial phases + π/2",
            PAPER._replace(start_ramp_s=1.5, start_lean=True, start_phase_rad=float(np.pi / 2))),
    Variant("lean_ramp", "cpgjax's lean_ramp start-up: lean, blended out over a 3 s amplitude ramp",
            cpg.with_startup(PAPER, "lean_ramp")),
)


class Gaits(NamedTuple):
    """Gaits to restart, each with the instance's conditions."""

    params: np.ndarray  # (n, 8)
    instance: np.ndarray  # (n,) the study's instance
    trial: np.ndarray  # (n,) the trial it walked (its scenario)
    slope_deg: np.ndarray  # (n,)
    controller: np.ndarray  # (n,) str


def gait_sets(columns: dict[str, np.ndarray]) -> dict[str, Gaits]:
    """The two sets of the module docstring from a study's trials (``study_io.read_trials``)."""
    fell = (columns["fell"] > 0) | (columns["failed"] > 0)
    optimized = columns["inference"] == 0
    slope = columns["slope_deg"]
    params = np.stack([columns[name] for name in param_space.PARAM_NAMES], axis=-1)
    after_fall, walked = {}, {}
    for t, b in zip(*np.nonzero(fell[:-1] & optimized[:-1] & optimized[1:] & (slope[1:] == slope[:-1])
                                & (slope[:-1] > 0)), strict=True):
        earlier = [k for k in range(t) if not fell[k, b] and slope[k, b] == slope[t, b]]
        if earlier:
            k = earlier[-1]
            after_fall.setdefault(params[k, b].tobytes(), (k, b))
    for k, b in zip(*np.nonzero(optimized & ~fell & (slope > 0)), strict=True):
        walked.setdefault(params[k, b].tobytes(), (k, b))

    def gaits(found: dict) -> Gaits:
        kb = np.array(list(found.values()), int).reshape(-1, 2)
        k, b = kb[:, 0], kb[:, 1]
        return Gaits(params=params[k, b], instance=b, trial=k, slope_deg=slope[k, b],
                     controller=np.asarray(columns["controller"])[k, b])
    return {"after a fall": gaits(after_fall), "walked": gaits(walked)}


def restart(engine: ablation.Engine, gaits: Gaits, variant: Variant, backend: str) -> np.ndarray:
    """(n,) bool: the gait fell in its trial from standing under ``variant``."""
    fields = [getattr(engine.scenario(int(t)), f)[int(b)] for t, b in zip(gaits.trial, gaits.instance, strict=True)
              for f in go1_model.Scenario._fields]
    width = len(go1_model.Scenario._fields)
    scenario = go1_model.Scenario(*(np.array(fields[i::width]) for i in range(width)))
    sim = backends.make_backend(scenario, backend, variant.config, engine.spec.trial)
    start = np.tile(param_space.midpoint(), (len(gaits.params), 1)) if variant.blend_from_midpoint else gaits.params
    _, record = sim.trial(sim.reset(start), gaits.params, protocol.batch_gates(list(gaits.controller)))
    record = ablation.fetch(record)
    return (np.asarray(record.fell) > 0) | (np.asarray(record.failed) > 0)


def table(folder: pathlib.Path, study: str, variants: tuple[Variant, ...], backend: str) -> str:
    """The markdown table of the module docstring."""
    from cpgjax.studies import driver as study_driver  # the study's scenarios (its file)

    engine = ablation.Engine(study_driver.read(study).spec, backend="native")
    sets = gait_sets(study_io.read_trials(folder / "trials.parquet"))
    slopes = sorted(set(np.concatenate([g.slope_deg for g in sets.values()]).tolist()))
    head = " | ".join(f"{name}, {s:g}°" for name in sets for s in slopes)
    lines = [f"| start-up | change | {head} |", "|---|---|" + "---|" * (len(sets) * len(slopes))]
    paper = {}
    for variant in variants:
        cells = []
        for name, gaits in sets.items():
            fell = restart(engine, gaits, variant, backend)
            for s in slopes:
                here = gaits.slope_deg == s
                starts, n = int((~fell[here]).sum()), int(here.sum())
                cell = f"{starts}/{n} ({stats.proportion_ci(starts, n)})"
                if variant.name == "paper":
                    paper[name, s] = (starts, n)
                elif (name, s) in paper:
                    cell += f", p = {stats.fisher_p(starts, n, *paper[name, s]):.2g}"
                cells.append(cell)
        lines.append(f"| {variant.name} | {variant.change} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=pathlib.Path, help="a slope study's output folder (with trials.parquet)")
    parser.add_argument("--study", default="slope_adaptation", help="the study the folder ran (a name or a file)")
    parser.add_argument("--backend", default="native", choices=backends.BACKENDS)
    parser.add_argument("--variants", default=",".join(v.name for v in VARIANTS),
                        help="comma-separated, from: " + ", ".join(v.name for v in VARIANTS))
    args = parser.parse_args(argv)
    by_name = {v.name: v for v in VARIANTS}
    chosen = args.variants.split(",")
    unknown = [n for n in chosen if n not in by_name]
    if unknown:
        parser.error(f"--variants: unknown {', '.join(unknown)}; allowed: {', '.join(by_name)}")
    print(table(args.folder, args.study, tuple(by_name[n] for n in chosen), args.backend))


if __name__ == "__main__":
    main()
