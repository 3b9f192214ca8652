"""One online optimization (``cpgjax optimize``) as a study of the protocol (``registry.Study``): one engine run of
one instance (``OptimizeOptions.spec``), nothing walked again, a report of its trials and its best, and the file a
replay reads (``best_params.json``, :mod:`cpgjax.trial.tuned`) with the recording (docs/outputs.md).
"""

from __future__ import annotations

import pathlib

import numpy as np

from cpgjax import ablation
from cpgjax.studies import options as study_options
from cpgjax.studies import registry
from cpgjax.study import files as study_io
from cpgjax.trial import params as param_space
from cpgjax.trial import tuned


def trials_table(trial_log: study_io.TrialLog) -> str:
    """Markdown table of one optimization's trials (instance 0), numbered from 0 as in trials.parquet."""
    lines = ["| trial | J | v_x [m/s] | CoT | c_load [N] | c_slope [rad] | β | fell |", "|---" * 8 + "|"]
    for t in range(trial_log.objective.shape[0]):
        lines.append(
            f"| {t} | {trial_log.objective[t, 0]:.3f} | {trial_log.velocity_xy_mps[t, 0, 0]:.3f} | "
            f"{trial_log.cot[t, 0]:.3f} | {trial_log.context[t, 0, 0]:.1f} | "
            f"{trial_log.context[t, 0, 1]:.3f} | {trial_log.beta[t, 0]:.3g} | {bool(trial_log.fell[t, 0])} |"
        )
    return "\n".join(lines)


def best_trial(trial_log: study_io.TrialLog) -> int:
    """The trial with the highest J of one optimization (instance 0)."""
    return int(np.argmax(trial_log.objective[:, 0]))


def write_best_params(path: pathlib.Path, trial_log: study_io.TrialLog, tuned_for: dict, **info) -> int:
    """``best_params.json`` of one optimization (instance 0) in the format ``cpgjax deploy --params`` replays, with
    what it was tuned for (:mod:`cpgjax.trial.tuned`) and ``info``; returns the best trial."""
    best = best_trial(trial_log)
    tuned.save(
        path, trial_log.params[best, 0], tuned_for, objective=float(trial_log.objective[best, 0]), trial=best, **info
    )
    return best


def report(result: ablation.StudyResult) -> str:
    """The trials' table and the best trial's J and parameters."""
    tr = result.trials
    best = best_trial(tr)
    return (
        f"{trials_table(tr)}\nbest J {tr.objective[best, 0]:.3f} at trial {best}: "
        f"{param_space.as_dict(tr.params[best, 0])}"
    )


def _write(result: ablation.StudyResult, options: study_options.OptimizeOptions, text: str, out: pathlib.Path) -> str:
    feet = {} if options.foot_friction is None else {"foot_friction": options.foot_friction}
    with study_io.writing(out, tuned.FILE_NAME):
        write_best_params(out / tuned.FILE_NAME, result.trials, options.tuned_for(), **feet)
    with study_io.writing(out, study_io.RECORDING):
        study_io.write_recording(result, out / study_io.RECORDING)
    return text


def study(options: study_options.OptimizeOptions) -> registry.Study:
    """The optimization ``options`` describe, as a study of the protocol."""
    spec = options.spec()
    return registry.Study(
        spec.name,
        (spec,),
        registry.walks_nothing,
        lambda results, evaluation: report(registry.only(results)),
        lambda results, evaluation, text, out, notify: _write(registry.only(results), options, text, out),
        written_by="optimize",
    )
