"""stgc: Spacetime Gaussians with spatiotemporal KNN compaction, measured.

Layers (a package imports only from its own layer or below; tests/test_layers.py checks it, docs/architecture.md):
cli | demo | experiment -> eval -> train | compaction | codec -> model -> data | render -> errors | fileio | config | run
(one known exception: the trainer uses stgc.eval for SSIM and its end-of-training evaluation)
"""

import ctypes as _ctypes
import os as _os

# torch and numba run OpenMP regions (on torch's libgomp, one pool, once torch is loaded; numba's layer binds to it);
# with the default (active) wait policy idle threads busy-wait and steal the cores that other work needs (a 50k
# render measured 5.1 s instead of 0.28 s under load). Must be set before libgomp loads, i.e. before torch is imported.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def _keep_freed_memory() -> None:
    """glibc's malloc returns freed blocks of more than a few MB to the OS, so the next render's per-Gaussian and
    per-pixel arrays come back as fresh pages, each zeroed by a page fault (about 5 us a page on the virtual
    machines measured: a 6 MB array 7 ms, and two threads faulting at once wait on each other). Blocks up to 32 MiB
    (glibc's largest mmap threshold) then come from the heap, which keeps up to 256 MiB free at the top of each of
    its arenas. The user's own settings win: MALLOC_MMAP_THRESHOLD_, MALLOC_TRIM_THRESHOLD_ or the same in
    GLIBC_TUNABLES (glibc reads them when the process starts); not glibc (macOS, musl): nothing to do. Importing
    stgc sets this for the whole process, like OMP_WAIT_POLICY above."""
    tunables = _os.environ.get("GLIBC_TUNABLES", "")
    if ("MALLOC_MMAP_THRESHOLD_" in _os.environ or "MALLOC_TRIM_THRESHOLD_" in _os.environ
            or "malloc.mmap_threshold" in tunables or "malloc.trim_threshold" in tunables):
        return
    try:
        mallopt = _ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):
        return
    m_trim_threshold, m_mmap_threshold = -1, -3  # malloc.h
    mallopt(m_mmap_threshold, 32 << 20)
    mallopt(m_trim_threshold, 256 << 20)


_keep_freed_memory()

__version__ = "0.1.0"
