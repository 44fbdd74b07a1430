#!/bin/bash
# Interleaved rasterizer A/B, 50k Gaussians, C = 9, 256x256, 1 and 2 threads: worktree $1 against worktree $2,
# rounds $3, then any extra benchmark flags (--stages: the split by kernel). Run from the repository root.
#   rast_ab.sh <A> <B> 3 > rast_ab.log;   rast_ab.sh <A> <B> 3 --stages > rast_stages_ab.log
A=$1; B=$2; R=${3:?rounds}; shift 3
for r in $(seq 1 $R); do
  for t in 1 2; do
    for side in A B; do
      src=$A; [ $side = B ] && src=$B
      echo "round $r side $side threads $t $(uptime | sed 's/.*load/load/')"
      PYTHONPATH=$src/src .venv/bin/python $src/benchmarks/rasterizer.py --n 50000 --size 256x256 --channels 9 \
        --backends numba --repeats 15 --threads $t "$@" 2>&1 | grep -E "^\| (numba|50k) "
    done
  done
done
