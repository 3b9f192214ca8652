"""Each group's best gait of a finished study: the gait a replay runs (``best_params/<group>.json``), a video films
and the recording shows, and the per-step logs of such gaits walked again.

A best gait is one that walked: a trial that did not fall and whose J is above the objective's floor
(``objective.MIN_OBJECTIVE``, where a trial that stood still or walked backwards ends). Per group: the latest phase
(the stretch between two condition changes, before a ramp) in which some run has a trial that walked; of the runs
with one, the run with the best final objective, and its best trial there that walked. Only where no trial of the
group walked is another picked, and the gait's file says so (``walked``: false).
"""

from __future__ import annotations

import dataclasses
import pathlib
import re

import numpy as np

from cpgjax import ablation
from cpgjax.go1 import constants
from cpgjax.go1 import model as go1_model
from cpgjax.go1 import terrain as terrains
from cpgjax.studies import registry
from cpgjax.studies import video as study_video
from cpgjax.study import spec as study_spec
from cpgjax.trial import objective, protocol
from cpgjax.trial.condition import Condition


def group_name(labels: dict, spec: study_spec.StudySpec) -> str:
    """A group's name in file names: its ``group_by`` label values joined by ``_`` (a controller by name, a schedule
    by its name where the study gives one, other labels as label + value), arrows as ``-`` and anything else but
    letters, digits, ``.``, ``-`` and ``_`` dropped."""
    names = {s.label: s.name for s in spec.schedules if s.name}
    parts = [
        str(labels[k])
        if k == "controller"
        else names[labels[k]]
        if k == "schedule" and labels[k] in names
        else f"{k}{labels[k]}"
        for k in spec.group_by
    ]
    return re.sub(r"[^A-Za-z0-9._-]", "", "_".join(parts).replace("→", "-"))


Phase = tuple[int, int]  # (first trial, last + 1)


def group_names(result) -> np.ndarray:
    """(B,) each instance's group name (:func:`group_name`)."""
    return np.array([group_name(lab, result.spec) for lab in result.labels])


def phases(result) -> list[list[Phase]]:
    """Each instance's phases: (first, last + 1) of each stretch between its schedule's condition changes, from the
    study's own conditions (a ramp's slopes and, with domain randomization, the drawn friction and payload start no
    phase)."""
    cond = study_spec.conditions(dataclasses.replace(result.spec, randomize=None))
    n = result.trials.objective.shape[0]
    fields = [cond.slope_deg, cond.target_velocity_mps, cond.inference, cond.ramp]
    if result.spec.randomize is None:
        fields += [cond.friction, cond.payload_kg]
    out = []
    for b in range(len(result.labels)):
        starts = sorted({t for f in fields for t in registry.phase_starts(np.asarray(f[b, :n]))})
        out.append(list(zip(starts, starts[1:] + [n], strict=True)))
    return out


def phase_text(result, b: int, phase: Phase) -> str:
    """A phase as the reports write it: its trials and conditions."""
    cond, (start, stop) = result.walked, phase
    mode = ", inference mode" if cond.inference[b, start] else ""
    return (
        f"trials {start}–{stop - 1}: {registry.friction_text(float(cond.friction[b, start]), result.labels[b])}, "
        f"{cond.slope_deg[b, start]:g}°, "
        f"{cond.payload_kg[b, start]:g} kg, v* {cond.target_velocity_mps[b, start]:g} m/s{mode}"
    )


def best_run(result, mask: np.ndarray, all_phases: list[list[Phase]]) -> tuple[int, int, Phase, bool]:
    """(instance, trial, phase, walked) of the group ``mask``'s best gait (the module's rule), given every instance's
    :func:`phases`; the trials on a ramp do not count (their slopes differ by instance and trial)."""
    tr = result.trials
    stop = registry.ramp_start(result)
    final = registry.last_mean(tr.objective, stop)
    runs = {int(b): [(s, min(e, stop)) for s, e in all_phases[b] if s < stop] for b in np.flatnonzero(mask)}
    for k in range(1, max(len(p) for p in runs.values()) + 1):
        walking = {
            b: [t for t in range(*p[-k]) if tr.fell[t, b] == 0 and tr.objective[t, b] > objective.MIN_OBJECTIVE]
            for b, p in runs.items()
            if len(p) >= k
        }
        walking = {b: ts for b, ts in walking.items() if ts}
        if walking:
            b = max(walking, key=lambda b: final[b])
            return b, max(walking[b], key=lambda t: tr.objective[t, b]), runs[b][-k], True
    b = max(runs, key=lambda b: final[b])
    start, end = runs[b][-1]
    return b, start + int(np.argmax(tr.objective[start:end, b])), runs[b][-1], False


def best_gaits(result) -> list[study_video.Gait]:
    """Per group of the study (``spec.group_by``): its best gait (:func:`best_run`) in the conditions of its trial."""
    tr, cond = result.trials, result.walked
    names, all_phases = group_names(result), phases(result)
    gaits = []
    for name in dict.fromkeys(names):
        b, t, phase, walked = best_run(result, names == name, all_phases)
        condition = Condition(
            friction=float(cond.friction[b, t]),
            slope_deg=float(cond.slope_deg[b, t]),
            payload_kg=float(cond.payload_kg[b, t]),
            target_velocity_mps=float(cond.target_velocity_mps[b, t]),
            gait=str(result.labels[b]["gait"]),
            foot_friction=float(result.labels[b]["foot_friction"]),
            ground=study_spec.ground(result.labels[b]),
        )
        gaits.append(
            study_video.Gait(
                group=str(name),
                params=np.asarray(tr.params[t, b], np.float64),
                controller=result.labels[b]["controller"],
                physics=str(result.labels[b]["physics"]),
                condition=condition,
                transition_steps=result.spec.trial.transition_steps,
                steady_steps=result.spec.trial.steady_steps,
                objective=float(tr.objective[t, b]),
                instance=b,
                trial=t,
                phase=phase_text(result, b, phase),
                walked=walked,
            )
        )
    return gaits


def save_gaits(out: pathlib.Path, result: ablation.StudyResult, gaits: list[study_video.Gait]) -> None:
    """Each group's best gait (:func:`best_gaits`) as ``out/best_params/<group>.json``, what ``deploy --params`` and
    ``walk --params`` replay as tuned and what the study films (``best_<group>.mp4``)."""
    for gait in gaits:
        study_video.save_gait(out, gait, seed=int(result.labels[gait.instance]["seed"]), study=result.spec.name)


def gait_rollouts(gaits: list[study_video.Gait], backend: str, steps: int | None = None) -> list:
    """The per-step logs of ``gaits`` (one batch), each on its ground: a settling trial of the gaits' lengths, then
    ``steps`` ticks (default: the steady phase's length, 3 s in the paper's trial)."""
    config = protocol.TrialConfig(transition_steps=gaits[0].transition_steps, steady_steps=gaits[0].steady_steps)
    if any((g.transition_steps, g.steady_steps) != (config.transition_steps, config.steady_steps) for g in gaits):
        raise study_spec.StudyError("the gaits were found with different trial lengths; film them one at a time")
    conditions = [g.condition for g in gaits]
    scenario = go1_model.make_scenarios(
        friction=[c.friction for c in conditions],
        slope_deg=[c.slope_deg for c in conditions],
        payload_kg=[c.payload_kg for c in conditions],
        physics=[g.physics for g in gaits],
        foot_friction=[c.foot_friction for c in conditions],
        **terrains.ground_fields(c.ground for c in conditions),
    )
    return registry.rollouts(
        np.stack([g.params for g in gaits]),
        [g.controller for g in gaits],
        scenario,
        config,
        backend,
        config.steady_steps if steps is None else steps,
        [c.gait for c in conditions],
    )


def film(path: pathlib.Path, gait: study_video.Gait, backend: str, seconds: float) -> dict:
    """The MP4 ``path`` of ``gait``: ``seconds`` of it after a settling trial (:func:`gait_rollouts`), rendered by
    ``study_video.render_videos``, whose info it returns.

    Raises:
      study_video.RenderUnavailable, RuntimeError: as ``study_video.render_videos``.
    """
    (log,) = gait_rollouts([gait], backend, steps=constants.ticks(seconds))
    (info,) = study_video.render_videos([study_video.Job(path=path, qpos=log.qpos, condition=gait.condition)])
    return info
