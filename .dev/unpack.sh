#!/bin/bash
# unpack.sh DIR: put the runs that finish.sh carried back (DIR/*.tgz, each holding e.g. noise/RUN/) into results/,
# replacing those folders; a finished run (metrics.csv at its config's epochs) keeps no checkpoint there, an
# unfinished one keeps its carried checkpoint (docs/usage.md); the compilation cache goes to .xla/
set -eu
cd "$(dirname "$0")/.."
for t in "$1"/*.tgz; do
  [ "$(basename "$t")" = xla.tgz ] && { rm -f .xla/xla.tgz; mkdir -p .xla; cp "$t" .xla/xla.tgz; continue; }
  run=$(tar tzf "$t" | grep -m1 '/config.json$'); run=${run%/config.json}
  [[ "$run" == ?*/?* ]] || { echo "skip $t: no RUN/config.json inside"; continue; }
  rm -rf "results/$run"; mkdir -p "results/$(dirname "$run")"
  tar xzf "$t" -C results "$run"
  if python3 - "results/$run" <<'PY'
import csv, json, sys
run = sys.argv[1]
epochs = json.load(open(f"{run}/config.json"))["run"]["epochs"]
rows = list(csv.DictReader(open(f"{run}/metrics.csv")))
sys.exit(0 if rows and float(rows[-1]["epoch"]) >= epochs else 1)
PY
  then rm -rf "results/$run/checkpoints"; echo "results/$run: finished (its checkpoints not kept)"
  else echo "results/$run: unfinished, keeps $(ls "results/$run/checkpoints" 2>/dev/null | tr '\n' ' ')"; fi
done
git add -A results
git status --short results | grep -v '/checkpoints/' || true
