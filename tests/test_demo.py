"""`make demo`'s pipeline (stgc.demo) around the plan runner: what it reports."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest

import stgc.demo as demo
from stgc.experiment.runner import PlanResult, RunOutcome


def test_the_demo_renders_its_video_again_after_a_new_training(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    video = tmp_path / "test_view.mp4"
    video.write_bytes(b"rendered from last week's model")
    os.utime(video, (1e9, 1e9))
    compacted = tmp_path / "st-knn"
    compacted.mkdir()
    (compacted / "train_summary.json").write_text("{}")  # trained now

    def trained_again(data: Any, plan: Any, out_dir: Any, **kwargs: Any) -> PlanResult:
        result = PlanResult(plan, Path(out_dir))
        result.outcomes = [RunOutcome("st-knn", "ST-KNN", "Case 2", "finished", compacted, {}, record={"psnr": 30.0})]
        return result

    rendered: list[Path] = []
    monkeypatch.setattr(demo, "run_plan", trained_again)
    monkeypatch.setattr(demo, "render_video", lambda run, path: rendered.append(path))
    demo.run_demo(tmp_path)
    assert rendered == [video]
