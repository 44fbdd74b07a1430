import platform

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
