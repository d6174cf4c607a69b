"""The command lines, grouped by role: `run`, `evaluate` and `plot` here (with `cli` and `report`,
what they share), the paper's experiments in `paper/`, benchmarks in `bench/`, probes in `probes/`
(docs/usage.md lists every command)."""
