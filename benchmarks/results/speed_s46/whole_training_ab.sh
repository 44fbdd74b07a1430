#!/bin/bash
# Whole blender_toys cpu-preset trainings at 2 threads, one after the other: the session's start code, then the fused rows.
cd "$(git rev-parse --show-toplevel)"
for pair in "head:<a16ef01>/src" "new:<525a143>/src"; do
  name=${pair%%:*}; src=${pair#*:}
  PYTHONPATH=$src .venv/bin/python -m stgc.cli train ../shared/data/blender_toys --out runs/s46/bl-$name --preset cpu --set train.threads=2 > runs/s46/bl-$name.log 2>&1
done
