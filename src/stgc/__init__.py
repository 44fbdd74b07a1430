"""stgc: Spacetime Gaussians with spatiotemporal KNN compaction, measured.

Layers (a package imports only from its own layer or below; tests/test_layers.py checks it, docs/architecture.md):
cli | demo | experiment -> eval -> train | compaction | codec -> model -> data | render -> errors | fileio | config | run
(one known exception: the trainer uses stgc.eval for SSIM and its end-of-training evaluation)
"""

import os as _os

# torch and numba each run an OpenMP pool; with the default (active) wait policy the idle pool busy-waits and
# steals the cores the other one needs (a 50k render measured 5.1 s instead of 0.28 s). Must be set before
# either library starts its threads, i.e. before torch is imported.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
