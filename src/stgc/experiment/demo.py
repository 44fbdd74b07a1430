"""`stgc demo`: the whole pipeline on the small embedded scene (demo/toys_small), resumable.

Two trainings (plain STG, and STG with ST-KNN compaction Case 2), each evaluated on the held-out camera and
compressed to `.stgc` at the codec's default quality, then the report (table, RD plot, BD deltas) in OUT/report.
It is `run_plan` with a two-run plan, so an interrupted demo continues where it stopped.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Sequence

from stgc.experiment.plans import Plan, RunSpec
from stgc.experiment.runner import run_plan

DEMO_SCENE = Path(__file__).resolve().parents[3] / "demo" / "toys_small"


def demo_plan() -> Plan:
    common = {"data.preprocess": "none"}
    return Plan(
        "demo",
        (
            RunSpec("stg", {**common, "compaction.method": "none"}, "STG", "Trained model"),
            RunSpec("st-knn-case2", {**common, "compaction.method": "st-knn", "compaction.case": "2",
                                     "compaction.criterion": "timestamp"}, "ST-KNN", "Case 2"),
        ),
        baseline="STG",
        title="Demo: STG vs ST-KNN compaction on demo/toys_small",
    )


def run_demo(out: Path, data: Path | None = None, preset: str = "cpu",
             extra_overrides: Sequence[str] = (), codec_qualities: Sequence[int] | None = None) -> int:
    """Run the demo into `out`; 0 when every step succeeded, 1 otherwise."""
    if codec_qualities is None:
        from stgc.codec import DEFAULT_QUALITY  # noqa: PLC0415

        codec_qualities = (DEFAULT_QUALITY,)
    scene = data or DEMO_SCENE
    result = run_plan(scene, demo_plan(), out, preset=preset, extra_overrides=list(extra_overrides),
                      codec_qualities=codec_qualities)
    print(result)
    if result.report is not None:
        print()
        print(result.report.markdown.read_text())
    if result.failed:
        print(f"stgc demo: {len(result.failed)} step(s) failed; see {out / 'logs'}", file=sys.stderr)
        return 1
    return 0
