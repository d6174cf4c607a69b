#!/bin/bash
# lane.sh REPO QUEUE: run QUEUE's lines (python -m arguments; $REPO expands) one after another from outside the
# source tree; SIGTERM the running one at the deadline; skip what would start with under 240 s left
REPO=$1; cd /tmp/wd
while read -r line; do
  [ -z "$line" ] && continue
  left=$(( $(cat /tmp/lanes/deadline) - $(date +%s) ))
  if [ $left -lt 240 ]; then echo "$(date +%T) skip: $line"; continue; fi
  echo "$(date +%T) start ($left s left): $line"
  eval "exec python3 -m $line" &
  pid=$!; rc=
  while kill -0 $pid 2>/dev/null; do
    if [ $(date +%s) -ge $(cat /tmp/lanes/deadline) ]; then kill -TERM $pid; echo "$(date +%T) SIGTERM"; wait $pid; rc=$?; break; fi
    sleep 5
  done
  [ -z "$rc" ] && { wait $pid; rc=$?; }
  echo "$(date +%T) exit $rc: $line"
done < "$2"
echo "$(date +%T) LANE_DONE"
