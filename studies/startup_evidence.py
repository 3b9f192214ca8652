"""Where a restart from standing on a slope (or under a load) goes wrong, and which start-up fixes it
(docs/decisions.md §18): the gaits that walked a condition in a finished study, each restarted from standing on that
condition under one change of the start at a time.

    python studies/startup_evidence.py results/slope_adaptation [--backend native|mjx] [--variants paper,lean_ramp]
        [--limit N]
    python studies/startup_evidence.py results/load_adaptation --study load_adaptation

Two sets of gaits per condition (a slope > 0 or a payload > 0, with the other), from the folder's
``trials.parquet`` (optimized trials):

* ``after a fall``: the instance's last gait that walked the condition before a fall (the restarts the study could
  not avoid, as ``studies/fall_chains.py --rewalk`` picks them), each gait once;
* ``walked``: every distinct gait that walked the condition.

Each gait then runs one trial (1.5 s transition + 3 s, the study's timing and physics) from standing on its
condition, the transition from the gait itself (no blend) unless a variant says otherwise; it "starts" if the trial
does not fall. The table gives, per variant, set and condition, the starts out of the gaits with the
Clopper–Pearson 95 % interval, and Fisher's exact p against the paper's start.
"""

from __future__ import annotations

import argparse
import pathlib
from typing import NamedTuple

import numpy as np

from cpgjax import ablation, cpg
from cpgjax.sim import backends
from cpgjax.studies import driver as study_driver
from cpgjax.studies import stats
from cpgjax.study import files as study_io
from cpgjax.study import placement as study_placement
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
    Variant("paper", "the paper's start: r = 0.1 → μ at α = 50, trot phases, feet 3.5 cm behind the hips, VMC at once"),
    Variant(
        "blend",
        "the 1.5 s blend starts from the box midpoint (as after a fall, from another gait)",
        blend_from_midpoint=True,
    ),
    Variant("ramp", "amplitude target ramps 0 → μ over 1.5 s", PAPER._replace(start_ramp_s=1.5)),
    Variant("ramp_3s", "amplitude target ramps 0 → μ over 3 s", PAPER._replace(start_ramp_s=3.0)),
    Variant(
        "phase",
        "initial phases + π/2 (the first pair starts mid-swing)",
        PAPER._replace(start_phase_rad=float(np.pi / 2)),
    ),
    Variant(
        "lean",
        "standing posture leans into the slope: feet shifted by h·tan(pitch) in x",
        PAPER._replace(start_lean=True),
    ),
    Variant("vmc_delay", "VMC off for the first 1.5 s", PAPER._replace(start_vmc_delay_s=1.5)),
    Variant("kp", "K_p 70 → 100 N·m/rad (everywhere)", PAPER._replace(kp_nm_rad=100.0)),
    Variant(
        "ramp_lean",
        "lean, blended out over a 1.5 s amplitude ramp",
        PAPER._replace(start_ramp_s=1.5, start_lean=True, start_lean_s=1.5),
    ),
    Variant(
        "ramp_lean_phase",
        "lean blended out over a 1.5 s ramp, initial phases + π/2",
        PAPER._replace(start_ramp_s=1.5, start_lean=True, start_lean_s=1.5, start_phase_rad=float(np.pi / 2)),
    ),
    Variant(
        "lean_blend",
        "lean, blended out over 3 s; the amplitude as the paper's",
        PAPER._replace(start_lean=True, start_lean_s=3.0),
    ),
    Variant(
        "lean_ramp",
        "cpgjax's lean_ramp start-up: lean, blended out over a 3 s amplitude ramp",
        cpg.with_startup(PAPER, "lean_ramp"),
    ),
)


class Gaits(NamedTuple):
    """Gaits to restart, each with the instance's conditions."""

    params: np.ndarray  # (n, 8)
    instance: np.ndarray  # (n,) the study's instance
    trial: np.ndarray  # (n,) the trial it walked (its scenario)
    condition: np.ndarray  # (n,) str: its slope and payload, as the table's column
    controller: np.ndarray  # (n,) str


def condition_labels(columns: dict[str, np.ndarray]) -> np.ndarray:
    """Each trial's condition (T, B) as a label, "" on level ground without a load."""
    slope, payload = columns["slope_deg"], columns["payload_kg"]
    label = np.vectorize(lambda s, m: ", ".join(([f"{s:g}°"] if s else []) + ([f"{m:g} kg"] if m else [])))
    return label(slope, payload)


def gait_sets(columns: dict[str, np.ndarray]) -> dict[str, Gaits]:
    """The two sets of the module docstring from a study's trials (``study_io.read_trials``)."""
    fell = (columns["fell"] > 0) | (columns["failed"] > 0)
    optimized = columns["inference"] == 0
    condition = condition_labels(columns)
    params = np.stack([columns[name] for name in param_space.PARAM_NAMES], axis=-1)
    after_fall, walked = {}, {}
    for t, b in zip(
        *np.nonzero(
            fell[:-1] & optimized[:-1] & optimized[1:] & (condition[1:] == condition[:-1]) & (condition[:-1] != "")
        ),
        strict=True,
    ):
        earlier = [k for k in range(t) if not fell[k, b] and condition[k, b] == condition[t, b]]
        if earlier:
            k = earlier[-1]
            after_fall.setdefault(params[k, b].tobytes(), (k, b))
    for k, b in zip(*np.nonzero(optimized & ~fell & (condition != "")), strict=True):
        walked.setdefault(params[k, b].tobytes(), (k, b))

    def gaits(found: dict) -> Gaits:
        kb = np.array(list(found.values()), int).reshape(-1, 2)
        k, b = kb[:, 0], kb[:, 1]
        return Gaits(
            params=params[k, b],
            instance=b,
            trial=k,
            condition=condition[k, b],
            controller=np.asarray(columns["controller"])[k, b],
        )

    return {"after a fall": gaits(after_fall), "walked": gaits(walked)}


def restart(engine: ablation.Engine, gaits: Gaits, variant: Variant, backend: str) -> np.ndarray:
    """(n,) bool: the gait fell in its trial from standing under ``variant``."""
    scenario = engine.batch.scenario_at(gaits.trial, gaits.instance)
    sim = backends.make_backend(scenario, backend, variant.config, engine.spec.trial)
    start = np.tile(param_space.midpoint(), (len(gaits.params), 1)) if variant.blend_from_midpoint else gaits.params
    _, record = sim.trial(sim.reset(start), gaits.params, protocol.batch_gates(list(gaits.controller)))
    record = study_placement.fetch(record)
    return (np.asarray(record.fell) > 0) | (np.asarray(record.failed) > 0)


def evenly(gaits: Gaits, limit: int | None) -> Gaits:
    """At most ``limit`` of the gaits, evenly spaced in the set's order (all of them without a limit)."""
    if limit is None or len(gaits.params) <= limit:
        return gaits
    keep = np.linspace(0, len(gaits.params) - 1, limit).round().astype(int)
    return Gaits(*(field[keep] for field in gaits))


def table(
    folder: pathlib.Path, study: str, variants: tuple[Variant, ...], backend: str, limit: int | None = None
) -> str:
    """The markdown table of the module docstring (at most ``limit`` gaits per set, :func:`evenly`)."""
    engine = ablation.Engine(study_driver.read(study).spec, backend="native")
    sets = {name: evenly(g, limit) for name, g in gait_sets(study_io.read_trials(folder / "trials.parquet")).items()}
    conditions = sorted(set(np.concatenate([g.condition for g in sets.values()]).tolist()))
    head = " | ".join(f"{name}, {s}" for name in sets for s in conditions)
    lines = [f"| start-up | change | {head} |", "|---|---|" + "---|" * (len(sets) * len(conditions))]
    paper = {}
    for variant in variants:
        cells = []
        for name, gaits in sets.items():
            fell = restart(engine, gaits, variant, backend)
            for s in conditions:
                here = gaits.condition == s
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
    parser.add_argument("folder", type=pathlib.Path, help="a study's output folder (with trials.parquet)")
    parser.add_argument("--study", default="slope_adaptation", help="the study the folder ran (a name or a file)")
    parser.add_argument("--backend", default="native", choices=backends.BACKENDS)
    parser.add_argument(
        "--variants",
        default=",".join(v.name for v in VARIANTS),
        help="comma-separated, from: " + ", ".join(v.name for v in VARIANTS),
    )
    parser.add_argument(
        "--limit",
        type=int,
        default=None,
        help="at most this many gaits per set, evenly spaced (a smaller batch for MJX on a CPU, where it is slow)",
    )
    args = parser.parse_args(argv)
    if args.limit is not None and args.limit < 1:
        parser.error(f"--limit {args.limit}: need at least 1 gait per set")
    by_name = {v.name: v for v in VARIANTS}
    chosen = args.variants.split(",")
    unknown = [n for n in chosen if n not in by_name]
    if unknown:
        parser.error(f"--variants: unknown {', '.join(unknown)}; allowed: {', '.join(by_name)}")
    print(table(args.folder, args.study, tuple(by_name[n] for n in chosen), args.backend, args.limit))


if __name__ == "__main__":
    main()
