#!/bin/bash
# Interleaved rasterizer A/B: base worktree ($1) against new ($2), rounds $3.
A=$1; B=$2; R=${3:-3}
for r in $(seq 1 $R); do
  for t in 1 2; do
    for side in A B; do
      src=$A; [ $side = B ] && src=$B
      echo "round $r side $side threads $t $(uptime | sed 's/.*load/load/')"
      PYTHONPATH=$src/src .venv/bin/python $src/benchmarks/rasterizer.py --n 50000 --size 256x256 --channels 9 --backends numba --repeats 15 --threads $t 2>&1 | grep "^| numba"
    done
  done
done
