"""The command lines, grouped by role: `run`, `evaluate` and `plot` here (with `cli` and `report`,
what they share), the paper's experiments in `paper/`, benchmarks in `bench/`, probes in `probes/`
(docs/usage.md lists every command)."""

import os
import sys

# `python -m experiments.<command>` (Python names the module "-m" while it imports this package to find it): XLA's
# and absl's C++ logs (the GPU autotuner's dumps, rematerialization warnings) stay off the terminal, since every
# failure is one `error:` line; set before JAX loads, never on a library import. TF_CPP_MIN_LOG_LEVEL=0 shows them.
if sys.argv[:1] == ["-m"]:
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
