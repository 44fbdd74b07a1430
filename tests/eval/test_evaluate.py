"""The evaluation driver on a fake renderer: per-view numbers against numpy, aggregates, written files."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from stgc.errors import DataError
from stgc.eval import (
    evaluate,
    evaluate_run,
    format_eval_table,
    model_size,
    write_eval,
)
from stgc.model.layout import ply_fields
from stgc.run import Run


@dataclass
class FakeCam:
    name: str
    frame: int
    time: float
    image: str | None = None


def _gt(cam: FakeCam) -> np.ndarray:
    rng = np.random.default_rng(100 * int(cam.name[-1]) + cam.frame)
    return (rng.random((16, 20, 3)) * 255).astype(np.uint8)


def _noisy_render(cam: FakeCam) -> torch.Tensor:
    noise = 0.02 * (1 + int(cam.name[-1]))
    rng = np.random.default_rng(cam.frame)
    img = _gt(cam) / 255.0 + noise * rng.standard_normal((16, 20, 3))
    return torch.from_numpy(img).float()  # unclamped, as a renderer gives it


CAMS = [FakeCam(f"cam{c}", f, f / 4) for c in (0, 1) for f in range(4)]


def _numpy_psnr(cam: FakeCam) -> float:
    a = np.clip(_noisy_render(cam).numpy().astype(np.float64), 0, 1)
    b = _gt(cam) / 255.0
    return float(10 * np.log10(1.0 / np.mean((a - b) ** 2)))


def test_evaluate_scores_every_view() -> None:
    result = evaluate(_noisy_render, CAMS, _gt, warmup=1)
    assert len(result.views) == 8
    for view, cam in zip(result.views, CAMS):
        assert view.psnr == pytest.approx(_numpy_psnr(cam), abs=1e-4)
        assert 0 < view.ssim < 1
    assert result.psnr == pytest.approx(np.mean([_numpy_psnr(c) for c in CAMS]), abs=1e-4)
    # Noisier camera scores worse; per-camera means are means of their own views.
    assert result.per_camera["cam0"]["psnr"] > result.per_camera["cam1"]["psnr"]
    assert result.per_camera["cam1"]["psnr"] == pytest.approx(np.mean([_numpy_psnr(c) for c in CAMS[4:]]), abs=1e-4)
    assert result.speed is not None and result.speed.frames_timed == 7
    assert result.lpips_note.startswith("skipped")


def test_evaluate_accepts_model_render_objects_and_rejects_size_mismatch() -> None:
    class Out:
        def __init__(self, rgb: torch.Tensor) -> None:
            self.rgb = rgb

    r = evaluate(lambda c: Out(torch.from_numpy(_gt(c) / 255.0)), CAMS[:2], _gt)
    assert r.views[0].psnr == float("inf") and r.ssim == pytest.approx(1.0)
    # One exact view among others counts at the ceiling: the mean stays finite (it was inf, and the record null).
    from stgc.eval.evaluate import PSNR_CEILING_DB

    mixed = evaluate(lambda c: _gt(c) / 255.0 if c.frame == 0 else _noisy_render(c), CAMS[:2], _gt)
    assert mixed.views[0].psnr == float("inf")
    assert mixed.psnr == pytest.approx((PSNR_CEILING_DB + mixed.views[1].psnr) / 2)
    assert mixed.overall["psnr_yuv"] is not None and math.isfinite(mixed.overall["psnr_yuv"])
    with pytest.raises(DataError, match="ground-truth"):
        evaluate(lambda c: torch.zeros(8, 8, 3), CAMS[:1], _gt)


def test_a_render_holding_nan_is_refused_naming_its_view() -> None:
    """One NaN pixel scored PSNR null (a perfect render's), SSIM NaN (invalid JSON) and a plausible YUV-PSNR."""
    from stgc.errors import StgcError

    def broken(cam: FakeCam) -> torch.Tensor:
        rgb = torch.from_numpy(_gt(cam) / 255.0)
        rgb[0, 0, 0] = float("nan")
        return rgb

    with pytest.raises(StgcError, match=f"camera {CAMS[0].name} frame {CAMS[0].frame}: the render holds non-finite"):
        evaluate(broken, CAMS[:1], _gt)


def test_write_eval_files(tmp_path: Path) -> None:
    (tmp_path / "train_summary.json").write_text(json.dumps({"iterations": 50, "wall_seconds": 3.0, "finished": True}))
    result = evaluate(_noisy_render, CAMS, _gt)
    returned = write_eval(tmp_path, result, model_size(1000, "full", duration_s=1.0, decoder_floats=90))
    record = json.loads((tmp_path / "eval.json").read_text())
    assert returned == record
    text = format_eval_table(record)
    for key in ("psnr", "ssim", "num_gaussians", "size_mb", "mbps", "fps", "size_mib", "size_mb_si", "train_seconds"):
        assert key in record
    assert record["num_gaussians"] == 1000 and record["train_seconds"] == 3.0
    assert record["size_mb"] == pytest.approx((1000 * 152 + 360) / 2**20)
    assert record["psnr"] == pytest.approx(result.psnr)
    with open(tmp_path / "eval_per_view.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 8 and rows[0]["camera"] == "cam0" and float(rows[0]["psnr"]) == pytest.approx(
        result.views[0].psnr, abs=1e-4)
    assert "PSNR" in text and "all" in text
    assert not list(tmp_path.glob(".*.tmp"))


def test_eval_paths_for_bitstreams(tmp_path: Path) -> None:
    run = Run(tmp_path)
    assert run.eval_paths() == (tmp_path / "eval.json", tmp_path / "eval_per_view.csv")
    j, c = run.eval_paths(bitstream=tmp_path / "model_q5.stgc")
    assert j == tmp_path / "eval_model_q5.json" and c == tmp_path / "eval_model_q5_per_view.csv"
    assert run.eval_paths("other")[0] == tmp_path / "eval_on_other.json"


class FakeModel:
    num_gaussians, variant = 7, "lite"

    def __init__(self) -> None:
        self.backends: set[str] = set()

    def render(self, cam: FakeCam, t: float, background: torch.Tensor, backend: str = "auto") -> torch.Tensor:
        assert t == cam.time
        self.backends.add(backend)
        return _noisy_render(cam)


class FakeDataset:
    test, frames, fps, background = CAMS, list(range(4)), 2.0, (0.0, 0.0, 0.0)
    root = "fake_data"

    def load_image(self, cam: FakeCam) -> np.ndarray:
        return _gt(cam)


def _seven_gaussian_run(run: Path) -> None:
    """RUN/point_cloud/iteration_10 holding a 7-row lite model (what FakeModel renders)."""
    it = run / "point_cloud" / "iteration_10"
    it.mkdir(parents=True)
    rows = np.zeros(7, dtype=[(n, "f4") for n in ply_fields("lite")])
    PlyData([PlyElement.describe(rows, "vertex")]).write(str(it / "point_cloud.ply"))


def test_evaluate_run_with_injected_model_and_dataset(tmp_path: Path) -> None:
    _seven_gaussian_run(tmp_path)
    it = tmp_path / "point_cloud" / "iteration_10"
    record = evaluate_run(tmp_path, load_model=lambda p: FakeModel(), open_dataset=lambda p: FakeDataset())
    assert record["num_gaussians"] == 7 and record["duration_s"] == 2.0 and record["video_fps"] == 2.0  # 4 frames
    assert record["file_bytes"] == {"point_cloud.ply": (it / "point_cloud.ply").stat().st_size}
    assert record["mbps"] == pytest.approx(7 * 128 * 8 / 1e6 / 2.0)
    assert record["fps"] > 0
    assert (tmp_path / "eval.json").is_file() and "all" in format_eval_table(record)
    # A saved model's PLY named itself is scored into its folder (it rendered every view, then could not write
    # PLY/eval.json).
    record = evaluate_run(it / "point_cloud.ply", load_model=lambda p: FakeModel(), open_dataset=lambda p: FakeDataset(),
                          measure_fps=False)
    assert record["num_gaussians"] == 7 and (it / "eval.json").is_file()
    stgc = tmp_path / "model_q3.stgc"
    stgc.write_bytes(_bitstream({}))
    record = evaluate_run(stgc, load_model=lambda p: FakeModel(), open_dataset=lambda p: FakeDataset(),
                          measure_fps=False)
    assert record["size_bytes"] == stgc.stat().st_size and record["fps"] is None
    assert (tmp_path / "eval_model_q3.json").is_file()
    # Rendered with the backend the run trained with, as its trainer's evaluation (FPS of one table compare).
    (tmp_path / "config.json").write_text(json.dumps({"train": {"backend": "torch"}}))
    model = FakeModel()
    evaluate_run(stgc, load_model=lambda p: model, open_dataset=lambda p: FakeDataset(), measure_fps=False)
    assert model.backends == {"torch"}


def _bitstream(metadata: dict) -> bytes:
    from stgc.codec.format import encode
    from stgc.codec.synthetic import synthetic_model

    arrays, _ = synthetic_model(20, "lite", seed=1)
    return encode(arrays, "lite", None, 2, metadata=metadata)


def test_a_bitstream_record_names_the_iteration_it_holds(tmp_path: Path) -> None:
    """A .stgc of an earlier iteration (`stgc compress RUN/point_cloud/iteration_N`) was recorded with the run's
    final iterations, and reported as the finished run's codec point."""
    _seven_gaussian_run(tmp_path)
    (tmp_path / "config.json").write_text("{}")
    (tmp_path / "train_summary.json").write_text(json.dumps({"finished": True, "iterations": 20}))
    stgc = tmp_path / "model_q2.stgc"
    for iteration, final in ((5, False), (20, True)):
        stgc.write_bytes(_bitstream({"iteration": iteration}))
        record = evaluate_run(stgc, load_model=lambda p: FakeModel(), open_dataset=lambda p: FakeDataset(),
                              measure_fps=False)
        assert record["iterations"] == iteration and record["training_finished"] is final


def test_a_record_of_a_half_trained_run_says_so_and_is_not_the_finished_runs(tmp_path: Path, caplog) -> None:
    """`stgc eval` of a run still training scores its latest saved model: the record says the training had not
    finished, and once it has, that record is not taken for the finished model's (Run.evaluated_finished_model)."""
    _seven_gaussian_run(tmp_path)
    (tmp_path / "config.json").write_text("{}")

    def score() -> dict:
        return evaluate_run(tmp_path, load_model=lambda p: FakeModel(), open_dataset=lambda p: FakeDataset(),
                            measure_fps=False)

    with caplog.at_level("WARNING"):
        record = score()
    assert record["training_finished"] is False and "iterations" not in record
    assert "has not finished training" in caplog.text
    (tmp_path / "train_summary.json").write_text(json.dumps({"finished": True, "iterations": 20}))
    assert not Run(tmp_path).evaluated_finished_model()  # the record scored the half-trained model
    record = score()
    assert record["training_finished"] is True and record["iterations"] == 20
    assert Run(tmp_path).evaluated_finished_model()


def test_a_whole_videos_render_rate_is_all_renders_over_all_their_time() -> None:
    from stgc.eval.evaluate import aggregate_video_records

    # Each segment timed its renders after 2 warm-up ones.
    fast = {"psnr": 30.0, "num_views": 52, "fps": 100.0, "duration_s": 1.0, "size_bytes": 10,
            "render_speed": {"frames_timed": 50}}
    slow = {"psnr": 20.0, "num_views": 52, "fps": 10.0, "duration_s": 1.0, "size_bytes": 10,
            "render_speed": {"frames_timed": 50}}
    video = aggregate_video_records([("segment_0", fast), ("segment_1", slow)])
    # 100 renders in 0.5 s + 5 s: 18.2 per second, not the mean of the rates (55).
    assert video["fps"] == pytest.approx(100 / 5.5)
    assert video["psnr"] == pytest.approx(25.0)
