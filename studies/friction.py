"""The paper's friction result: ``cpgjax.study.registry.STUDIES["friction"]`` (see that module for what it runs and writes).

    python studies/friction.py [--quick] [--seeds N] [--trials N] [--out DIR] [--resume] [--backend auto|mjx|native]

Same as ``cpgjax study friction ...``; writes results/friction/ by default.
"""

import sys

from cpgjax import cli

if __name__ == "__main__":
    sys.exit(cli.main(["study", "friction", *sys.argv[1:]]))
