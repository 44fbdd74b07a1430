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


def test_a_demo_folder_from_another_stgc_version_is_refused_with_the_remedy(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """`make demo` has no --out: over a demo_out whose finished runs were made with other options (an older stgc's
    defaults) the plan runner rightly refuses to reuse them, and the demo must say how to go on, deleting nothing."""
    import json

    from stgc.experiment import runner

    old = tmp_path / "demo_out" / "stg"
    old.mkdir(parents=True)
    (old / "config.json").write_text(json.dumps({"data": {}, "model": {}, "train": {"iterations": 10},
                                                 "compaction": {"method": "st-knn"}}))
    trained: list[list[str]] = []

    def no_training(cmd: list[str], log_path: Path) -> int:
        trained.append(cmd)
        return 1

    real_run_plan = runner.run_plan
    monkeypatch.setattr(demo, "run_plan", lambda *a, **k: real_run_plan(*a, **{**k, "runner": no_training}))
    assert demo.run_demo(tmp_path / "demo_out") == 1
    assert f"rm -rf {tmp_path / 'demo_out'}" in caplog.text and "made with other options or data" in caplog.text
    assert (old / "config.json").is_file()
    assert all("stg" != Path(cmd[cmd.index("--out") + 1]).name for cmd in trained if "--out" in cmd)
