#!/bin/bash
# poll.sh SECONDS [DEADLINE_FROM_NOW]: optionally move the deadline, sleep, then show each lane's log tail
[ -n "${2:-}" ] && echo $(( $(date +%s) + $2 )) > /tmp/lanes/deadline
echo "deadline in $(( $(cat /tmp/lanes/deadline) - $(date +%s) )) s"
end=$(( $(date +%s) + $1 ))
while [ $(date +%s) -lt $end ]; do
  [ $(grep -l LANE_DONE /tmp/lanes/lane*.log 2>/dev/null | wc -l) -ge $(ls /tmp/lanes/lane*.log | wc -l) ] && break
  sleep 10
done
for f in /tmp/lanes/lane*.log; do
  echo "== $f"
  tr '\r' '\n' < $f | grep -vE "epoch/s|s/epoch" | grep -iE "start|exit|skip|SIGTERM|LANE|error|compiled|Traceback|final" | tail -8
  tr '\r' '\n' < $f | grep -E "epoch/s|s/epoch" | tail -1
done
nvidia-smi --query-gpu=index,utilization.gpu,memory.used --format=csv,noheader
