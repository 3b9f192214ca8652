"""The paper's load adaptation result: ``cpgjax.study.registry.STUDIES["load_adaptation"]`` (see that module for what it runs and writes).

    python studies/load_adaptation.py [--quick] [--seeds N] [--trials N] [--out DIR] [--resume] [--backend auto|mjx|native]

Same as ``cpgjax study load_adaptation ...``; writes results/load_adaptation/ by default.
"""

import sys

from cpgjax import cli

if __name__ == "__main__":
    sys.exit(cli.main(["study", "load_adaptation", *sys.argv[1:]]))
