#!/bin/bash
# The capture study (issue 11, session capture): run the queue file QUEUE one `radfield reconstruct`
# at a time, each line "NAME FROM DATASET [reconstruct options...]", into $STUDY/runs/NAME (default
# STUDY=/work/runs/capture), OMP_NUM_THREADS=1. FROM is a finished run directory whose upstream
# stages (sfm data triangulate envelope tetra init) are copied into the new run first: the pipeline's cache is
# by content, so they are reused when the new run's keys for them are the same (SfM once per
# capture), and re-run otherwise; "-" copies nothing. The queue is re-read after every run, so lines
# may be appended while it runs; names listed in $STUDY/started.txt are not run again.
# $STUDY/done.txt gets "NAME rc=RC wall=SECONDS"; the command of each run is in $STUDY/cmds/NAME.cmd.
#   usage: scripts/study/run_capture.sh QUEUE
set -u
queue=$(realpath "$1")
root=$(cd "$(dirname "$0")/../.." && pwd)
STUDY=${STUDY:-/work/runs/capture}; RADFIELD="$root/.venv/bin/radfield"
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
mkdir -p "$STUDY/runs" "$STUDY/logs" "$STUDY/cmds"; touch "$STUDY/started.txt"
cd "$STUDY"
while true; do
  next=$(grep -v '^\s*\(#\|$\)' "$queue" | while read -r name rest; do
           grep -qx "$name" started.txt || { echo "$name $rest"; break; }; done)
  [ -z "$next" ] && break
  set -- $next
  name=$1 from=$2 ds=$3; shift 3
  echo "$name" >> started.txt
  if [ "$from" != "-" ] && [ ! -e "runs/$name" ]; then
    mkdir -p "runs/$name"
    cp "$from/radfield-run.json" "runs/$name/"
    for stage in sfm data triangulate envelope tetra init; do
      [ -d "$from/$stage" ] && cp -a "$from/$stage" "runs/$name/"
    done
  fi
  echo "$RADFIELD reconstruct $ds -o runs/$name -q $*  # stages from $from" > "cmds/$name.cmd"
  start=$(date +%s)
  "$RADFIELD" reconstruct "$ds" -o "runs/$name" -q "$@" > "logs/$name.out" 2> "logs/$name.err"
  echo "$name rc=$? wall=$(( $(date +%s) - start ))" >> done.txt
done
