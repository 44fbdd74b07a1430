#!/bin/bash
# usage: iteration_ab.sh DATA MODEL ITERATIONS ROUNDS THREADS SRC_A SRC_B ...  (each SRC: the src/ of a
# `git worktree add DIR COMMIT`, put on PYTHONPATH; ms per cpu-preset iteration at the steady state, interleaved)
cd "$(git rev-parse --show-toplevel)"
DATA=$1; MODEL=$2; IT=$3; ROUNDS=$4; TH=$5; shift 5
for r in $(seq $ROUNDS); do
  for src in "$@"; do
    ms=$(echo go | PYTHONPATH=$src .venv/bin/python -c '
import sys, tempfile, time
import stgc
from stgc import machine
from stgc.config import parse_set_arguments
from stgc.options import resolve_configs
sys.path.insert(0, "benchmarks")
from iteration_profile import steady_state_trainer
data, model_path, iterations, threads = sys.argv[1:5]
machine.use_threads(int(threads))
with tempfile.TemporaryDirectory() as out:
    trainer, start = steady_state_trainer(data, model_path, resolve_configs("cpu", {}, {}, parse_set_arguments([])), out)
    for i in range(start, start + 10):
        trainer.train_step(i)
    t0 = time.perf_counter()
    for i in range(start + 10, start + 10 + int(iterations)):
        trainer.train_step(i)
print(f"{(time.perf_counter() - t0) * 1e3 / int(iterations):.1f}")
' $DATA $MODEL $IT $TH 2>/dev/null | tail -1)
    echo "round $r $src: $ms ms (load $(cut -d' ' -f1 /proc/loadavg))"
  done
done
