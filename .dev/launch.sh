#!/bin/bash
# launch.sh SECONDS: install the carried wheels, then start one lane per queue file .dev/queueN.txt on GPU N, each
# stopping its command with SIGTERM at the deadline in /tmp/lanes/deadline (now + SECONDS; poll.sh may move it)
set -u
REPO=$(pwd)
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl .whl/own/*.whl || exit 1
mkdir -p /tmp/xla /tmp/lanes /tmp/wd /root/res
# train OUTSIDE the copied tree: every later call copies the tree again, restoring tracked files and deleting
# untracked ones there (session 24 lost 46 epochs so); queue lines write into /root/res/...
[ -d /root/res/noise ] || cp -r results/. /root/res/
for set in $(ls .xla/*.tgz.part* 2>/dev/null | sed 's/\.part[0-9]*$//' | sort -u); do cat "$set".part* | tar xzf - -C /tmp/xla; done
touch /tmp/lanes/start  # finish.sh carries back the cache entries newer than this
echo $(( $(date +%s) + $1 )) > /tmp/lanes/deadline
nvidia-smi --query-gpu=index,name,memory.used --format=csv
for q in .dev/queue[0-9].txt; do
  lane=${q#.dev/queue}; lane=${lane%.txt}
  CUDA_VISIBLE_DEVICES=$lane PYTHONPATH=/tmp/site BIDAL_JAX_CACHE=/tmp/xla PYTHONUNBUFFERED=1 \
    setsid nohup bash .dev/lane.sh "$REPO" "$REPO/.dev/queue$lane.txt" > /tmp/lanes/lane$lane.log 2>&1 < /dev/null &
done
sleep 2; echo launched
