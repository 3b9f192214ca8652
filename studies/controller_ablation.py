"""The paper's controller ablation result: ``cpgjax.study.registry.STUDIES["controller_ablation"]`` (see that module for what it runs and writes).

    python studies/controller_ablation.py [--quick] [--seeds N] [--trials N] [--out DIR] [--resume] [--backend auto|mjx|native]

Same as ``cpgjax study controller_ablation ...``; writes results/controller_ablation/ by default.
"""

import sys

from cpgjax import cli

if __name__ == "__main__":
    sys.exit(cli.main(["study", "controller_ablation", *sys.argv[1:]]))
