"""Projection benchmark: the numba projection (forward + hand-written backward) against the torch projection it
replaced in the numba backend, in one run.

Both take the same Gaussians (tests/render/scenes.py: depth U[3, 7] over the frustum, pixel sigma log-uniform in
[1, 6], random rotations) into a 320x180 camera and backpropagate (means2d.sum() + conics.sum()) to means, quats and
scales. Times are medians over repeats after one warm-up; "CPU ms" is process CPU time over all threads, which
another job on the machine disturbs far less than wall time (the figure to compare on a shared machine).

    .venv/bin/python benchmarks/projection.py                 # 10k and 50k Gaussians, 1 thread
    .venv/bin/python benchmarks/projection.py --n 30000 --threads 2
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numba  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from render.scenes import make_scene  # noqa: E402

from stgc import machine  # noqa: E402
from stgc.render.numba_backend import project_numba  # noqa: E402
from stgc.render.projection import project_gaussians  # noqa: E402


def measure(project, scene, repeats: int) -> tuple[float, float]:
    def once() -> None:
        s = scene.leaves()
        p = project(s.means, s.quats, s.scales, s.opacities, scene.K, scene.viewmat, scene.width, scene.height,
                    eps2d=0.3, near_plane=0.2)  # fmt: skip
        (p.means2d.sum() + p.conics.sum()).backward()

    once()
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        once()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall) * 1e3, statistics.median(cpu) * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, nargs="+", default=[10000, 50000])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=9)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    print(f"threads {args.threads}, machine: {machine.one_line()}")
    print(f"{'N':>7} {'torch ms':>9} {'torch CPU ms':>13} {'numba ms':>9} {'numba CPU ms':>13} {'CPU ratio':>10}")
    for n in args.n:
        scene = make_scene(n, width=320, height=180, channels=9, seed=1)
        t_wall, t_cpu = measure(project_gaussians, scene, args.repeats)
        n_wall, n_cpu = measure(project_numba, scene, args.repeats)
        print(f"{n:>7} {t_wall:>9.2f} {t_cpu:>13.2f} {n_wall:>9.2f} {n_cpu:>13.2f} {t_cpu / n_cpu:>9.1f}x")


if __name__ == "__main__":
    main()
