#!/bin/bash
# finish.sh RUNDIR...: wait for the lanes, then write into $OUT (the lending tool brings back at most 8 files of
# 16 MiB, 64 MiB together, named in letters, digits, '.', '_' and '-' alone): lanes.tgz (the lanes' logs); each
# RUNDIR (relative to /root/res, e.g. noise/RUN) as noise-RUN.tgz holding noise/RUN/, without its buffer, and
# without any checkpoint where experiments.carry.keeps_checkpoint says the run needs none (a finished run); the
# compilation cache entries this lease wrote, as xla.tgz.partNN (parts of 15 MiB). Run again in a later call of the
# same lease (after one that ran out of time: what it had written in $OUT came back), it packs the same copies again
REPO=/root/res; DEV=$(cd "$(dirname "$0")" && pwd); export PYTHONPATH=/tmp/site
end=$(( $(date +%s) + ${FINISH_WAIT:-120} ))  # a lift epoch in flight at the deadline takes up to about 60 s
while [ $(grep -l LANE_DONE /tmp/lanes/lane*.log 2>/dev/null | wc -l) -lt $(ls /tmp/lanes/lane*.log | wc -l) ] && [ $(date +%s) -lt $end ]; do sleep 3; done
tar czf $OUT/lanes.tgz -C /tmp/lanes .
cd /tmp/wd; mkdir -p /tmp/carry
for d in "$@"; do
  d=${d%/}; n=${d//\//-}  # noise/RUN -> noise-RUN.tgz, holding noise/RUN/ (unpack.sh extracts it into results/)
  [ -d "$REPO/$d" ] || continue
  mkdir -p "/tmp/carry/$(dirname $d)"
  # a copy an earlier finish.sh of this lease made (in a call that ran out of time) is packed as it is
  if [ ! -d "/tmp/carry/$d" ]; then
    # keeps.sh exit 3: a finished run, carried without checkpoints; 0 or a failure: with its latest one
    rc=0; bash "$DEV/keeps.sh" "$REPO/$d" || rc=$?
    if [ $rc = 3 ]; then cp -r "$REPO/$d" /tmp/carry/$d; rm -rf /tmp/carry/$d/checkpoints
    elif ls "$REPO/$d/checkpoints" >/dev/null 2>&1; then
      python3 -m experiments.carry --run-dir "$REPO/$d" --out /tmp/carry/$d \
        || { cp -r "$REPO/$d" /tmp/carry/$d; find /tmp/carry/$d -type d -name buffer -prune -exec rm -rf {} +; }
    else cp -r "$REPO/$d" /tmp/carry/$d; fi
  fi
  tar czf $OUT/$n.tgz --exclude=tb -C /tmp/carry $d
done
# the cache: the entries this lease wrote (newer than launch.sh's start), in parts of 15 MiB (xla.tgz.partNN);
# none where every program hit the carried cache
cd /tmp/xla && find . -type f -newer /tmp/lanes/start > /tmp/new.lst && [ -s /tmp/new.lst ] \
  && tar czf /tmp/xla-new.tgz -T /tmp/new.lst && split -b 15M -d /tmp/xla-new.tgz $OUT/xla.tgz.part
ls -la $OUT
