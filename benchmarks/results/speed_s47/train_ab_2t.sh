#!/bin/bash
# Whole blender_toys cpu-preset trainings at 2 threads, back to back, in the order given: train_ab_2t.sh C A
# (then TAG=-final train_ab_2t.sh D A). WT: the worktrees' prefix (worktree X is $WT$X).
cd "$(git rev-parse --show-toplevel)" && mkdir -p runs/s47
for s in "$@"; do
  echo "$s start $(date +%T) load $(cut -d' ' -f1-3 /proc/loadavg)"
  PYTHONPATH=${WT:?set WT}$s/src .venv/bin/python -m stgc.cli train ../shared/data/blender_toys --out runs/s47/bl-stg-2t-$s${TAG:-} --preset cpu --set train.threads=2 > runs/s47/bl-stg-2t-$s${TAG:-}.log 2>&1
  echo "$s end $(date +%T) load $(cut -d' ' -f1-3 /proc/loadavg)"
done
