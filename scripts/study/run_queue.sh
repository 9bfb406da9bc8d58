#!/bin/bash
# The issue-11 quality study: run the queue file QUEUE, one `radfield reconstruct` per line
# "NAME DATASET [reconstruct options...]", JOBS at a time (default 2), each with OMP_NUM_THREADS=1,
# into $STUDY/runs/NAME (default STUDY=/work/q). Finished runs are skipped (the pipeline caches them);
# $STUDY/done.txt gets "NAME rc=RC wall=SECONDS".
#   usage: scripts/study/run_queue.sh QUEUE [JOBS]
set -u
queue=$1; jobs=${2:-2}
root=$(cd "$(dirname "$0")/../.." && pwd)
export STUDY=${STUDY:-/work/q} RADFIELD="$root/.venv/bin/radfield" OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
mkdir -p "$STUDY/runs" "$STUDY/logs" "$STUDY/cmds"
grep -v '^\s*\(#\|$\)' "$queue" | xargs -P "$jobs" -L 1 bash -c '
  name=$0; ds=$1; shift
  cd "$STUDY"
  echo "$RADFIELD reconstruct $ds -o runs/$name -q $*" > cmds/$name.cmd
  start=$(date +%s)
  "$RADFIELD" reconstruct "$ds" -o "runs/$name" -q "$@" > "logs/$name.out" 2> "logs/$name.err"
  echo "$name rc=$? wall=$(( $(date +%s) - start ))" >> done.txt'
