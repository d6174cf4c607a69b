#!/bin/bash
# keeps.sh RUN: exit 0 when the results folder RUN keeps its latest checkpoint (experiments.carry.keeps_checkpoint:
# an unfinished run, a finished transfer source whose transfer arm has not started), 3 when it keeps none; any
# other exit (an import error) is a failure that the callers treat as "keep"
exec python3 -c 'import sys; from experiments.carry import keeps_checkpoint as k; sys.exit(0 if k(sys.argv[1]) else 3)' "$1"
