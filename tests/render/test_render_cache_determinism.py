"""The numba kernels give the same bits whether numba compiled them in the process or loaded them from its cache.

A resumed training (a new process, a warm cache) must continue bit for bit (tests/test_distributed.py). Session 47
measured that `fastmath={"contract"}` in the compositing backward broke this: LLVM fuses multiply-adds where the code
around them allows, so the kernel compiled in the process (helpers inlined) and the one loaded from the cache
rounded differently."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

RENDER_AND_DIGEST = """
import hashlib
import numba, torch
from stgc.render import rasterize
numba.set_num_threads(1)
torch.set_num_threads(1)
g = torch.Generator().manual_seed(0)
n = 3000
means = torch.cat([torch.rand(n, 2, generator=g) * 4 - 2, torch.rand(n, 1, generator=g) * 3 + 3], 1).requires_grad_()
quats = torch.randn(n, 4, generator=g).requires_grad_()
scales = (torch.rand(n, 3, generator=g) * 0.08 + 0.01).requires_grad_()
opacities = torch.rand(n, generator=g).requires_grad_()
features = torch.rand(n, 9, generator=g).requires_grad_()
K = torch.tensor([[80.0, 0, 40], [0, 80.0, 30], [0, 0, 1]])
out = rasterize(means, quats, scales, opacities, features, K, torch.eye(4), 80, 60, backend="numba")
(out.image * torch.rand(60, 80, 9, generator=g)).sum().backward()
digest = hashlib.sha256(out.image.detach().numpy().tobytes())
for t in (means, quats, scales, opacities, features):
    digest.update(t.grad.numpy().tobytes())
print(digest.hexdigest())
"""


def _digest(cache: Path) -> str:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    done = subprocess.run([sys.executable, "-c", RENDER_AND_DIGEST], env=env, capture_output=True, text=True,
                          timeout=600)  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout.strip().splitlines()[-1]


@pytest.mark.slow  # a fresh compile of the rasterizer's kernels: about 25 s
def test_kernels_compiled_in_the_process_and_loaded_from_the_cache_render_and_differentiate_identically(tmp_path):
    cache = tmp_path / "numba_cache"
    compiled = _digest(cache)
    cached_files = sorted(p.name for p in cache.rglob("*.nbc"))
    assert any("composite_backward" in name for name in cached_files), cached_files  # the second run loads them
    loaded = _digest(cache)
    assert len(compiled) == 64
    assert loaded == compiled
