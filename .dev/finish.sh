#!/bin/bash
# finish.sh RUNDIR...: wait for both lanes, carry each RUNDIR (relative to /root/res) without its buffer into $OUT
REPO=/root/res; export PYTHONPATH=/tmp/site
end=$(( $(date +%s) + 300 ))
while [ $(grep -l LANE_DONE /tmp/lanes/lane*.log 2>/dev/null | wc -l) -lt $(ls /tmp/lanes/lane*.log | wc -l) ] && [ $(date +%s) -lt $end ]; do sleep 3; done
cp /tmp/lanes/lane*.log $OUT/
cd /tmp/wd; mkdir -p /tmp/carry
for d in "$@"; do
  n=$(basename $d)
  [ -d "$REPO/$d" ] || continue
  if ls "$REPO/$d/checkpoints" >/dev/null 2>&1; then
    python3 -m experiments.carry --run-dir "$REPO/$d" --out /tmp/carry/$n || cp -r "$REPO/$d" /tmp/carry/$n
  else cp -r "$REPO/$d" /tmp/carry/$n; fi
  tar czf $OUT/$n.tgz --exclude=tb -C /tmp/carry $n
done
tar czf $OUT/xla.tgz -C /tmp/xla .
ls -la $OUT
