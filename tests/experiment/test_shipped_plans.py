"""Every plan shipped in benchmarks/plans/ resolves: a typo in one would otherwise surface only when someone runs it
(RESULTS cites their commands)."""

from __future__ import annotations

from pathlib import Path

import pytest

from stgc.experiment.plans import BUILTIN_PLANS, PAPER_PREPROCESS, load_plan
from stgc.experiment.runner import check_plan_options, finetune_overrides, run_overrides
from stgc.options import resolve_configs

PLANS = sorted((Path(__file__).resolve().parents[2] / "benchmarks" / "plans").glob("*.toml"))


def test_the_plans_folder_is_found():
    assert len(PLANS) >= 10


@pytest.mark.parametrize("path", PLANS, ids=[p.stem for p in PLANS])
def test_a_shipped_plan_loads_and_every_run_s_options_resolve(path, tmp_path):
    plan = load_plan(path)
    assert plan.runs
    check_plan_options(plan, "cpu", {}, tmp_path)


@pytest.mark.parametrize("path", PLANS, ids=[p.stem for p in PLANS])
def test_no_two_runs_of_a_shipped_plan_train_alike(path, tmp_path):
    """Two rows of one plan that resolve to the same configuration measure nothing between them: it happened when
    stgc's defaults changed under plans that had left an option to them (session 37's compaction defaults made a
    plan's probe-loss and probe-budget rows alike). The plans measured before a default changed pin its old value."""
    plan = load_plan(path)
    seen: dict[str, str] = {}
    for spec in plan.runs:
        overrides = run_overrides(plan, spec, {}, tmp_path)
        if spec.source is None:
            configs = resolve_configs("cpu", {}, {}, overrides)
            key = repr(sorted((section, repr(config)) for section, config in configs.items()))
        else:  # a fine-tuning: its source's model, its own options and length
            key = repr((spec.source, spec.iterations, sorted(finetune_overrides(spec, {}).items())))
        assert key not in seen, f"plan {plan.name!r}: runs {seen[key]!r} and {spec.name!r} train alike"
        seen[key] = spec.name


@pytest.mark.parametrize("path", PLANS, ids=[p.stem for p in PLANS])
def test_a_shipped_plan_s_run_named_as_a_paper_table_s_trains_as_that_table_does(path, tmp_path):
    """Plans run in Table 2's or 3's folder name its runs (finished runs are reused, others refused): each such
    entry must resolve to the table's configuration, or the plan is refused there and trains something else
    elsewhere (session 37's defaults did that to the learned-mask and no-preprocessing plans)."""
    tables = {spec.name: (plan, spec) for builder in BUILTIN_PLANS.values() for preprocess in ("none", PAPER_PREPROCESS)
              for plan in [builder(preprocess)] for spec in plan.runs}
    plan = load_plan(path)
    for spec in plan.runs:
        if spec.name in tables and spec.source is None:
            mine = resolve_configs("cpu", {}, {}, run_overrides(plan, spec, {}, tmp_path))
            if mine["compaction"].method == "reference":  # another plan's own unpruned reference, never a table's
                continue
            table, theirs = tables[spec.name]
            assert mine == resolve_configs("cpu", {}, {}, run_overrides(table, theirs, {}, tmp_path)), spec.name
