"""The paper's slope adaptation result: ``cpgjax.study.registry.STUDIES["slope_adaptation"]`` (see that module for what it runs and writes).

    python studies/slope_adaptation.py [--quick] [--seeds N] [--trials N] [--out DIR] [--resume] [--backend auto|mjx|native]

Same as ``cpgjax study slope_adaptation ...``; writes results/slope_adaptation/ by default.
"""

import sys

from cpgjax import cli

if __name__ == "__main__":
    sys.exit(cli.main(["study", "slope_adaptation", *sys.argv[1:]]))
