"""Plans of runs (the paper's tables or a PLAN.toml), run as independent resumable subprocesses, then the report."""

from stgc.experiment.plans import (
    BUILTIN_PLANS,
    Plan,
    RunSpec,
    load_plan,
    load_plan_toml,
    table2_plan,
    table3_plan,
)
from stgc.experiment.runner import (
    PlanResult,
    RunOutcome,
    build_compress_command,
    build_eval_command,
    build_train_command,
    run_is_finished,
    run_plan,
)

__all__ = [
    "BUILTIN_PLANS",
    "Plan",
    "PlanResult",
    "RunOutcome",
    "RunSpec",
    "build_compress_command",
    "build_eval_command",
    "build_train_command",
    "load_plan",
    "load_plan_toml",
    "run_is_finished",
    "run_plan",
    "table2_plan",
    "table3_plan",
]
