"""``make demo``: the paper's controller ablation — online optimization of the four CPG controllers — on the CPU.

Runs the ``--quick`` variant (4 controllers × 2 seeds × 12 trials of 1.5 s + 3 s: 41 s on the shared 2-core
development machine) because the full study (5 seeds × 40 trials, ``cpgjax study controller_ablation``) took 3.7 to
7.7 minutes there depending on the other jobs' load (docs/REPRODUCTION.md). Prints its table beside the paper's;
outputs go to ``results/demo_controller_ablation/``.
"""

import pathlib

from cpgjax import cli
from cpgjax.study import files as study_io


def main() -> None:
    out = pathlib.Path("results/demo_controller_ablation")
    print("cpgjax demo: online optimization (contextual GP-UCB, Algorithm 1) of the four CPG controllers at "
          "v* = 0.5 m/s, all runs batched in lockstep on the CPU (quick variant: 2 seeds × 12 trials; the first "
          "trials compile).", flush=True)
    (out / study_io.CHECKPOINT).unlink(missing_ok=True)  # the demo always computes afresh
    raise SystemExit(cli.main(["study", "controller_ablation", "--quick", "--out", str(out)]))


if __name__ == "__main__":
    main()
