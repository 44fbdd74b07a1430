#!/bin/bash
# Peak RSS of training iterations, per-view backward (A = 0603fd5, session 46's end) against one backward per batch
# (B = session 47's render_views). Usage: peak_rss.sh <A worktree> <B worktree>; run from the repository root.
set -e
for code in "$1" "$2"; do
  for row in "blender_toys runs/s39/bl-stg 2" "panoptic_basketball runs/s39/pan-stg 2" \
             "panoptic_basketball_640 runs/s39/pan-stg 2" "panoptic_basketball_640 runs/s39/pan-stg 4"; do
    set -- $row
    echo "code $(git -C "$code" rev-parse --short HEAD), data $1, model $2, train.batch $3:"
    PYTHONPATH="$code/src" .venv/bin/python benchmarks/results/speed_s48/peak_rss.py "$code/benchmarks" \
      --data "../shared/data/$1" --model "$2" --iterations 10 --set "train.batch=$3" 2>&1 | tail -n 1
  done
done
