import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest

from stgc import machine


@pytest.mark.parametrize(
    ("features", "expected"),
    [
        ({"avx512f": True, "avx2": True, "avx": True}, "avx512"),
        ({"avx512f": False, "avx2": True, "avx": True}, "avx2"),  # an AMD Zen 3 (session 22's host)
        ({"avx": True, "sse4.2": True}, "avx"),
        ({"neon": True}, "neon"),
        ({}, "scalar"),
    ],
)
def test_vector_isa_names_the_widest_feature_the_host_has(features, expected):
    assert machine.vector_isa(features) == expected


def test_describe_reads_this_host():
    found = machine.describe()
    assert found["cpus"] >= 1 and found["cpu_model"] and found["cpu_target"]
    if platform.machine() == "x86_64":
        assert found["vector_isa"] in {"avx512", "avx2", "avx", "sse4.2"}
    line = machine.one_line(found)
    assert found["cpu_target"] in line and f"{found['cpus']} CPUs" in line
    assert f"OpenMP {found['openmp_wait']}," in line
    older = {key: value for key, value in found.items() if key != "openmp_wait"}  # a summary from before the key
    assert "OpenMP" not in machine.one_line(older)


@pytest.mark.parametrize(
    ("environ", "expected"),
    [
        ({"OMP_WAIT_POLICY": "PASSIVE"}, "PASSIVE"),
        ({"OMP_WAIT_POLICY": "PASSIVE", "GOMP_SPINCOUNT": "3000"}, "PASSIVE+GOMP_SPINCOUNT=3000"),
        ({}, "unset"),
    ],
)
def test_openmp_wait_names_the_policy_and_a_spin_count(environ, expected):
    assert machine.openmp_wait(environ) == expected


def test_importing_stgc_makes_idle_openmp_threads_sleep_and_records_the_setting():
    # stgc sets the policy before torch can load its OpenMP runtime; the user's own setting wins. What a run
    # records is the setting at import, not a later change to the environment (libgomp has read it by then).
    probe = ("import os, stgc; from stgc import machine; os.environ['GOMP_SPINCOUNT'] = '7'; "
             "print(os.environ['OMP_WAIT_POLICY'], machine.describe()['openmp_wait'])")
    env = {key: value for key, value in os.environ.items() if key not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    assert subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True,
                          check=True).stdout.split() == ["PASSIVE", "PASSIVE"]
    env.update(OMP_WAIT_POLICY="ACTIVE", GOMP_SPINCOUNT="3000")
    assert subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True,
                          check=True).stdout.split() == ["ACTIVE", "ACTIVE+GOMP_SPINCOUNT=3000"]


_FAULTS_PER_ROUND = """
import resource
import numpy as np
from numpy._core import multiarray
import stgc
multiarray._set_madvise_hugepage(False)  # one fault per 4 kB page: the counts do not hinge on huge pages
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
counts = []
for _ in range(3):  # a render's arrays, over and over: per-Gaussian rows, images, pair lists of a few MB
    before = faults()
    for size in (3 << 20, 24 << 20, 6 << 20, 12 << 20):
        block = np.ones(size // 8)
        del block
    counts.append(faults() - before)
print(counts[1], counts[2])
"""


def _always_huge_pages() -> bool:
    try:
        return "[always]" in Path("/sys/kernel/mm/transparent_hugepage/enabled").read_text()
    except OSError:
        return False


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")
@pytest.mark.skipif(_always_huge_pages(), reason="the kernel backs every large block with huge pages: few faults")
def test_importing_stgc_keeps_freed_blocks_for_the_next_allocations_unless_the_user_set_glibcs_own():
    """Fresh pages cost a page fault each (stgc/__init__.py): after the first round the same allocations fault
    no more. With the user's own MALLOC_MMAP_THRESHOLD_ (glibc's default value here), stgc leaves malloc alone,
    and every round faults its 45 MB of pages in again (about 11,000)."""

    def later_rounds(extra_env):
        env = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"}
        out = subprocess.run([sys.executable, "-c", _FAULTS_PER_ROUND], env=env | extra_env, capture_output=True,
                             text=True, check=True)  # fmt: skip
        return [int(x) for x in out.stdout.split()]

    kept = later_rounds({})
    users_own = later_rounds({"MALLOC_MMAP_THRESHOLD_": "131072"})
    assert max(kept) < 100
    assert min(users_own) > 20 * (max(kept) + 1)
    assert min(later_rounds({"GLIBC_TUNABLES": "glibc.malloc.mmap_threshold=131072"})) > 20 * (max(kept) + 1)
