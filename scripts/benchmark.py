"""`python scripts/benchmark.py ...` == `pi0-jax benchmark ...` (see `--help`)."""

import sys

from pi0_jax.cli import main

if __name__ == "__main__":
    sys.exit(main(["benchmark", *sys.argv[1:]]))
