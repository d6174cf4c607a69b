#!/bin/bash
# unpack.sh DIR: put the runs that finish.sh carried back (DIR/*.tgz, each holding e.g. noise/RUN/) into results/,
# replacing those folders; then every run folder under results/ keeps its latest checkpoint only where
# experiments.carry.keeps_checkpoint says (an unfinished run, a finished transfer source whose transfer arm has not
# started; docs/usage.md); the compilation cache's parts (xla.tgz.partNN) join .xla/ as a set of their own, the
# lanes' logs go to /tmp/lanes-back
set -eu; shopt -s nullglob
cd "$(dirname "$0")/.."
mkdir -p .xla
# a lease's cache entries join those of earlier leases as one more set, .xla/xla-HASH.tgz.partNN, named by the
# parts' content so that unpacking the same files again (after a failure below) overwrites the set, not adds one
parts=("$1"/xla.tgz.part*)
if [ ${#parts[@]} -gt 0 ]; then
  hash=$(cat "${parts[@]}" | sha256sum | cut -c1-12)
  for f in "${parts[@]}"; do cp "$f" ".xla/xla-$hash.tgz.${f##*.tgz.}"; done
fi
[ -f "$1/lanes.tgz" ] && { mkdir -p /tmp/lanes-back; tar xzf "$1/lanes.tgz" -C /tmp/lanes-back; echo "lane logs in /tmp/lanes-back"; }
for t in "$1"/*.tgz; do
  [ "$(basename "$t")" = lanes.tgz ] && continue
  run=$(tar tzf "$t" | grep -m1 '/config.json$'); run=${run%/config.json}
  [[ "$run" == ?*/?* ]] || { echo "skip $t: no RUN/config.json inside"; continue; }
  rm -rf "results/$run"; mkdir -p "results/$(dirname "$run")"
  tar xzf "$t" -C results "$run"
done
# every run folder holding checkpoints, carried now or before (a transfer source is dropped once its arm has begun)
find results -type d -name checkpoints -prune | sort | while read -r dir; do
  run=${dir%/checkpoints}
  # exit 0: keep, 3: drop; anything else (an import error) stops here with the checkpoint untouched
  rc=0; bash .dev/keeps.sh "$run" || rc=$?
  case $rc in
    0) echo "$run: keeps checkpoint $(ls "$dir" | tr '\n' ' ')";;
    3) rm -rf "$dir"; echo "$run: finished, its checkpoints not kept";;
    *) echo "error: $run: keeps_checkpoint failed (exit $rc); nothing dropped, results/ not staged"; exit 1;;
  esac
done
git add -A results
git status --short results | grep -v '/checkpoints/' || true
