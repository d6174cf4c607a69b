#!/bin/bash
# finish.sh RUNDIR...: wait for the lanes, then write into $OUT (at most 8 files of 16 MiB, 64 MiB together):
# lanes.tgz (the lanes' logs); each RUNDIR (relative to /root/res, e.g. noise/RUN) as noise+RUN.tgz holding
# noise/RUN/, without its buffer, and without any checkpoint where experiments.carry.keeps_checkpoint says the
# run does not need one (a finished run); then the compilation cache entries this lease wrote, as xla-N.tgz
# parts of at most 15 MiB, while files and bytes remain
REPO=/root/res; export PYTHONPATH=/tmp/site
end=$(( $(date +%s) + 300 ))
while [ $(grep -l LANE_DONE /tmp/lanes/lane*.log 2>/dev/null | wc -l) -lt $(ls /tmp/lanes/lane*.log | wc -l) ] && [ $(date +%s) -lt $end ]; do sleep 3; done
tar czf $OUT/lanes.tgz -C /tmp/lanes .
cd /tmp/wd; mkdir -p /tmp/carry
for d in "$@"; do
  d=${d%/}; n=${d//\//+}  # noise/RUN -> noise+RUN.tgz, holding noise/RUN/ (unpack.sh extracts it into results/)
  [ -d "$REPO/$d" ] || continue
  mkdir -p "/tmp/carry/$(dirname $d)"
  # exit 3: a finished run, carried without checkpoints; 0 or a failure (an import error): with its latest one
  rc=0; python3 -c 'import sys; from experiments.carry import keeps_checkpoint as k; sys.exit(0 if k(sys.argv[1]) else 3)' \
    "$REPO/$d" || rc=$?
  if [ $rc = 3 ]; then cp -r "$REPO/$d" /tmp/carry/$d; rm -rf /tmp/carry/$d/checkpoints
  elif ls "$REPO/$d/checkpoints" >/dev/null 2>&1; then
    python3 -m experiments.carry --run-dir "$REPO/$d" --out /tmp/carry/$d || cp -r "$REPO/$d" /tmp/carry/$d
  else cp -r "$REPO/$d" /tmp/carry/$d; fi
  tar czf $OUT/$n.tgz --exclude=tb -C /tmp/carry $d
done
# the cache: entries newer than launch.sh's start, packed largest first into parts of at most 15 MiB
cd /tmp/xla; part=0; : > /tmp/part.lst; size=0
flush() { [ -s /tmp/part.lst ] || return 0
  files=$(ls $OUT | wc -l); used=$(du -sb $OUT | cut -f1)
  if [ $files -lt 8 ] && [ $(( used + size )) -lt $(( 62 * 1048576 )) ]; then
    tar czf $OUT/xla-$part.tgz -T /tmp/part.lst; part=$((part + 1))
  else echo "cache part left behind (files $files, bytes $used + $size)"; fi
  : > /tmp/part.lst; size=0; }
find . -type f -newer /tmp/lanes/start -printf '%s %p\n' | sort -rn > /tmp/new.lst
while read -r s f; do
  [ $(( size + s )) -gt $(( 15 * 1048576 )) ] && flush
  echo "$f" >> /tmp/part.lst; size=$(( size + s ))
done < /tmp/new.lst
flush
ls -la $OUT
