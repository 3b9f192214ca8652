"""Run a registry study with safe optimization at a β_s of one's choice (docs/decisions.md §17; the CLI's ``--safe``
uses ``OptimizerConfig.safe_beta``'s default, 2): the engine and ``trials.parquet`` only, to compare with
``studies/safe_comparison.py``.

    python studies/safe_beta.py slope_adaptation results/slope_adaptation_safe_beta3 --safe-beta 3
    python studies/safe_comparison.py results/slope_adaptation results/slope_adaptation_safe_beta3

The study is the registry's with its default seeds and trials, so its seeds are those of ``cpgjax study NAME``. A
non-empty output folder is refused unless ``--resume`` continues it or ``--overwrite`` replaces it.
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib
import sys

from cpgjax import ablation
from cpgjax.studies import driver as study_driver
from cpgjax.study import files as study_io
from cpgjax.study import spec as study_spec


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("study", help="a study file or a paper study: " + ", ".join(study_driver.paper_studies()))
    parser.add_argument("out", type=pathlib.Path, help="output folder")
    parser.add_argument("--safe-beta", type=float, required=True, help="β_s, the margin LCB multiplier (>= 0)")
    parser.add_argument("--resume", action="store_true", help="continue the run in OUT")
    parser.add_argument("--overwrite", action="store_true", help="replace the files in OUT")
    parser.add_argument("--quick", action="store_true", help="the study's quick variant (2 seeds, fewer trials)")
    args = parser.parse_args()
    try:
        spec = study_driver.read(args.study, quick=args.quick, safe=True).spec
        optimizer = dataclasses.replace(spec.optimizer_config(), safe_beta=args.safe_beta)
    except (study_spec.StudyError, ValueError) as err:
        print(f"safe_beta.py: {err}", file=sys.stderr)
        return 2
    spec = dataclasses.replace(spec, optimizer=optimizer)
    try:
        study_io.open_run(args.out, spec, "native", resume=args.resume, overwrite=args.overwrite)
    except (study_spec.StudyError, study_io.OutputError) as err:
        print(f"safe_beta.py: {err}", file=sys.stderr)
        return 1
    result = ablation.Engine(spec, backend="native").run(args.out, resume=args.resume)
    with study_io.writing(args.out, "trials.parquet"):
        study_io.write_trials(result, args.out / "trials.parquet")
    print(f"outputs in {args.out}/")
    return 0


if __name__ == "__main__":
    sys.exit(main())
