"""The paper's multi velocity result: ``cpgjax.study.registry.STUDIES["multi_velocity"]`` (see that module for what it runs and writes).

    python studies/multi_velocity.py [--quick] [--seeds N] [--trials N] [--out DIR] [--resume] [--backend auto|mjx|native]

Same as ``cpgjax study multi_velocity ...``; writes results/multi_velocity/ by default.
"""

import sys

from cpgjax import cli

if __name__ == "__main__":
    sys.exit(cli.main(["study", "multi_velocity", *sys.argv[1:]]))
