"""Every plan shipped in benchmarks/plans/ resolves: a typo in one would otherwise surface only when someone runs it
(RESULTS cites their commands)."""

from __future__ import annotations

from pathlib import Path

import pytest

from stgc.experiment.plans import load_plan
from stgc.experiment.runner import check_plan_options

PLANS = sorted((Path(__file__).resolve().parents[2] / "benchmarks" / "plans").glob("*.toml"))


def test_the_plans_folder_is_found():
    assert len(PLANS) >= 10


@pytest.mark.parametrize("path", PLANS, ids=[p.stem for p in PLANS])
def test_a_shipped_plan_loads_and_every_run_s_options_resolve(path, tmp_path):
    plan = load_plan(path)
    assert plan.runs
    check_plan_options(plan, "cpu", {}, tmp_path)
