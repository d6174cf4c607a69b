#!/bin/bash
# regen.sh: after unpack.sh, regenerate the paper experiments' tables, figures and the README's claims table from
# the run folders under results/ (each command is the one printed under its table), then stage them
set -euo pipefail  # a failing report stops here, not hidden by its tail
cd "$(dirname "$0")/.."
python -m experiments.paper.curves --report --out results/curves | tail -6
python -m experiments.paper.noise_robustness --report --out results/noise | tail -3
python -m experiments.paper.transfer_learning --arms none --out results/transfer --quiet | tail -12
python -m experiments.paper.claims --curves results/curves --noise results/noise --transfer results/transfer \
  --out results/claims.md --readme README.md | tail -4
git add -A results README.md
