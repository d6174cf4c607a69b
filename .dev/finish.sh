#!/bin/bash
# finish.sh RUNDIR...: wait for both lanes, carry each RUNDIR (relative to /root/res, e.g. noise/RUN) without its
# buffer into $OUT as a tarball holding that relative path (.dev/unpack.sh puts it back under results/)
REPO=/root/res; export PYTHONPATH=/tmp/site
end=$(( $(date +%s) + 300 ))
while [ $(grep -l LANE_DONE /tmp/lanes/lane*.log 2>/dev/null | wc -l) -lt $(ls /tmp/lanes/lane*.log | wc -l) ] && [ $(date +%s) -lt $end ]; do sleep 3; done
cp /tmp/lanes/lane*.log $OUT/
cd /tmp/wd; mkdir -p /tmp/carry
for d in "$@"; do
  d=${d%/}; n=${d//\//+}  # noise/RUN -> noise+RUN.tgz, holding noise/RUN/ (unpack.sh extracts it into results/)
  [ -d "$REPO/$d" ] || continue
  mkdir -p "/tmp/carry/$(dirname $d)"
  if ls "$REPO/$d/checkpoints" >/dev/null 2>&1; then
    python3 -m experiments.carry --run-dir "$REPO/$d" --out /tmp/carry/$d || cp -r "$REPO/$d" /tmp/carry/$d
  else cp -r "$REPO/$d" /tmp/carry/$d; fi
  tar czf $OUT/$n.tgz --exclude=tb -C /tmp/carry $d
done
tar czf $OUT/xla.tgz -C /tmp/xla .
ls -la $OUT
