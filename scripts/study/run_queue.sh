#!/bin/bash
# The issue-11 quality study: run the queue file QUEUE, one `radfield reconstruct` per line
# "NAME DATASET [reconstruct options...]", JOBS at a time (default 2), each with OMP_NUM_THREADS=1,
# into $STUDY/runs/NAME (default STUDY=/work/q). The queue is re-read whenever a slot frees, so
# lines may be appended while it runs; a `#` starts a comment, also after a line's options; a name
# listed in $STUDY/started.txt is not run again.
# $STUDY/done.txt gets "NAME rc=RC wall=SECONDS"; the command of each run is in $STUDY/cmds/NAME.cmd.
#   usage: scripts/study/run_queue.sh QUEUE [JOBS]
set -u
queue=$(realpath "$1"); jobs=${2:-2}
root=$(cd "$(dirname "$0")/../.." && pwd)
STUDY=${STUDY:-/work/q}; RADFIELD="$root/.venv/bin/radfield"
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
mkdir -p "$STUDY/runs" "$STUDY/logs" "$STUDY/cmds"; touch "$STUDY/started.txt"
cd "$STUDY"
run() {
  local name=$1 ds=$2; shift 2
  echo "$RADFIELD reconstruct $ds -o runs/$name -q $*" > "cmds/$name.cmd"
  local start=$(date +%s)
  "$RADFIELD" reconstruct "$ds" -o "runs/$name" -q "$@" > "logs/$name.out" 2> "logs/$name.err"
  echo "$name rc=$? wall=$(( $(date +%s) - start ))" >> done.txt
}
while true; do
  next=$(grep -v '^\s*\(#\|$\)' "$queue" | sed 's/[[:space:]]*#.*//' | while read -r name rest; do
           grep -qx "$name" started.txt || { echo "$name $rest"; break; }; done)
  [ -z "$next" ] && break
  # slots: every study run of this checkout counts, also those of an earlier runner
  while [ "$(pgrep -fc "$RADFIELD reconstruct")" -ge "$jobs" ]; do sleep 5; done
  set -- $next
  echo "$1" >> started.txt
  run "$@" &
  sleep 1
done
wait
