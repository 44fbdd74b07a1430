"""Whose model a record scored, and on which test set: a file of another model never stands for a run's result
(a PLY copied into a run, another run's .stgc in its folder), and a report never puts PSNRs of different test
sets on one curve or compares them, for `stgc report` and the experiment runner's rows alike."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from stgc.errors import DataError
from stgc.eval import evaluate_run
from stgc.eval.report import ReportRow, make_report, rate_points, record_fields, report_from_runs, rows_from_run
from stgc.model.layout import ply_fields


@dataclass
class Cam:
    name: str
    frame: int
    time: float
    image: str | None = None


CAMS = [Cam("cam0", f, f / 2) for f in range(2)]


def _image(cam: Cam) -> np.ndarray:
    return (np.random.default_rng(cam.frame).random((8, 10, 3)) * 255).astype(np.uint8)


class Model:
    num_gaussians, variant = 7, "lite"

    def render(self, cam: Cam, t: float, background: torch.Tensor, backend: str = "auto") -> torch.Tensor:
        return torch.from_numpy(_image(cam) / 255.0 * 0.9).float()


class Data:
    test, frames, fps, background, downscale = CAMS, [0, 1], 2.0, (0.0, 0.0, 0.0), 1.0

    def __init__(self, root: str | Path = "fake_data") -> None:
        self.root = root

    def load_image(self, cam: Cam) -> np.ndarray:
        return _image(cam)


def _score(target: Path, data: str | Path = "fake_data") -> dict[str, Any]:
    return evaluate_run(target, load_model=lambda p: Model(), open_dataset=lambda p: Data(data), measure_fps=False)


def _write_ply(path: Path, rows: int = 7) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    PlyData([PlyElement.describe(np.zeros(rows, dtype=[(n, "f4") for n in ply_fields("lite")]), "vertex")]).write(
        str(path))


def _run(root: Path, config: dict[str, Any] | None = None, iterations: int = 10) -> Path:
    """A finished run of a 7-Gaussian lite model, its config.json as given, evaluated."""
    _write_ply(root / "point_cloud" / f"iteration_{iterations}" / "point_cloud.ply")
    (root / "config.json").write_text(json.dumps(config if config is not None else CONFIG))
    (root / "train_summary.json").write_text(json.dumps({"finished": True, "iterations": iterations,
                                                         "wall_seconds": 5.0}))
    _score(root, ((config or {}).get("data") or {}).get("path") or "fake_data")
    return root


CONFIG = {"data": {"format": "auto", "downscale": 1.0, "start": 0, "duration": 2, "test_cameras": None,
                   "image_cache_mb": 2048},
          "model": {"variant": "lite"}, "train": {"iterations": 10}}


# ------------------------------------------------------------------------------ a PLY file in a run's folder


def test_a_ply_copied_into_a_run_is_refused_before_scoring_and_the_runs_record_stands(tmp_path: Path) -> None:
    """`stgc eval RUN/other.ply` wrote its scores into RUN/eval.json, stamped with the run's iterations and
    training_finished=True: reports and the experiment runner then took them for the run's result (and its size
    counted point_cloud.pt while the model loaded other.pt)."""
    run = _run(tmp_path / "run")
    before = (run / "eval.json").read_text()
    iteration = run / "point_cloud" / "iteration_10"
    loaded = []
    for stray in (run / "other.ply", iteration / "other.ply", run / "point_cloud.ply"):
        _write_ply(stray, rows=3)
        (stray.with_suffix(".pt")).write_bytes(b"")
        with pytest.raises(DataError, match="not a saved model of the run") as info:
            evaluate_run(stray, load_model=lambda p: loaded.append(p) or Model(), open_dataset=lambda p: Data(),
                         measure_fps=False)
        assert info.value.path == stray
        assert loaded == []  # refused before anything was loaded or rendered
    assert (run / "eval.json").read_text() == before
    assert not (iteration / "eval.json").exists()
    # The run's own saved model, named as its file, is scored beside it as before.
    assert _score(iteration / "point_cloud.ply")["num_gaussians"] == 7 and (iteration / "eval.json").is_file()


def test_only_a_folders_own_model_file_writes_the_record_of_a_folder_outside_any_run(tmp_path: Path) -> None:
    loose = tmp_path / "loose"
    _write_ply(loose / "model.ply")
    with pytest.raises(DataError, match="not a saved model of its folder"):
        _score(loose / "model.ply")
    assert not (loose / "eval.json").exists()
    _write_ply(loose / "point_cloud.ply")
    assert _score(loose / "point_cloud.ply")["num_gaussians"] == 7 and (loose / "eval.json").is_file()


def test_write_eval_refuses_to_file_another_models_scores_as_the_runs(tmp_path: Path) -> None:
    from stgc.eval import evaluate, write_eval

    run = _run(tmp_path / "run")
    _write_ply(run / "other.ply")
    result = evaluate(lambda cam: torch.zeros(8, 10, 3), CAMS, _image)
    with pytest.raises(DataError, match="not a saved model"):
        write_eval(run, result, target=run / "other.ply")
    assert json.loads((run / "eval.json").read_text())["training_finished"] is True


# ------------------------------------------------------------------------------ another run's .stgc


def _bitstream(path: Path, run_config: dict[str, Any] | None, iteration: int = 10, **more: Any) -> Path:
    from stgc.codec.format import encode
    from stgc.codec.synthetic import synthetic_model

    arrays, _ = synthetic_model(20, "lite", seed=1)
    metadata: dict[str, Any] = {"iteration": iteration, **more}
    if run_config is not None:
        metadata["run_config"] = run_config
    path.write_bytes(encode(arrays, "lite", None, 2, metadata=metadata))
    return path


def _embedded(config: dict[str, Any]) -> dict[str, Any]:
    return {key: config[key] for key in ("data", "model")}  # what `stgc compress` embeds


def test_another_runs_bitstream_in_a_runs_folder_is_recorded_as_foreign_and_not_reported(tmp_path: Path) -> None:
    """A file of run A (its config: 4 frames, test camera 3) in run C's folder was stamped training_finished=True
    with C's training time and reported as C's "+ codec" point."""
    data = tmp_path / "scene"
    data.mkdir()
    config = {**CONFIG, "data": {**CONFIG["data"], "path": str(data)}}
    run = _run(tmp_path / "run", config)
    other = {**config, "data": {**config["data"], "duration": 4, "test_cameras": "3"}}
    stgc = _bitstream(run / "model_q3.stgc", _embedded(other))
    record = _score(stgc)
    assert "data.duration 4 vs 2" in record["foreign"] and "data.test_cameras" in record["foreign"]
    assert record.get("training_finished") is None and record["train_seconds"] is None
    assert [row.extra.get("bitstream") for row in rows_from_run(run)] == [None]
    # The experiment runner makes its rows from the records alone: the report leaves the file out there too.
    rows = [ReportRow.from_mapping({**record_fields(json.loads((run / name).read_text())), "name": name,
                                    "family": family})
            for name, family in (("eval.json", "STG"), ("eval_model_q3.json", "STG + codec"))]
    report = make_report(rows, tmp_path / "report", baseline="STG")
    assert [row.name for row in report.rows] == ["eval.json"]
    assert "another run's model" in report.markdown.read_text()


def test_the_runs_own_bitstream_is_its_codec_point_also_after_its_data_moved(tmp_path: Path) -> None:
    old, new, elsewhere = tmp_path / "old", tmp_path / "new", tmp_path / "elsewhere"
    for folder in (old, elsewhere):
        folder.mkdir()
    config = {**CONFIG, "data": {**CONFIG["data"], "path": str(old)}}
    run = _run(tmp_path / "run", config)
    stgc = _bitstream(run / "model_q3.stgc", _embedded(config))
    record = _score(stgc, old)
    assert "foreign" not in record and record["training_finished"] is True and record["train_seconds"] == 5.0
    assert [row.extra.get("bitstream") for row in rows_from_run(run)] == [None, "model_q3.stgc"]
    # The data moved and the run was resumed there: its config.json names the new place (and another image cache,
    # an option of how it runs), the file the old one, which is gone.
    old.rename(new)
    moved = {**config, "data": {**config["data"], "path": str(new), "image_cache_mb": 64}}
    (run / "config.json").write_text(json.dumps(moved))
    record = _score(stgc, new)
    assert "foreign" not in record and record["training_finished"] is True
    # Both places there, and not one: another scene's run.
    new.rename(old)
    (run / "config.json").write_text(json.dumps({**config, "data": {**config["data"], "path": str(elsewhere)}}))
    assert "data.path" in _score(stgc)["foreign"]
    # A file written without its run config cannot be told apart: it is the folder's run's, as before.
    record = _score(_bitstream(run / "bare.stgc", None))
    assert "foreign" not in record and record["training_finished"] is True


def test_a_bitstream_of_another_run_of_the_same_config_is_told_apart_by_its_models_digest(tmp_path: Path) -> None:
    """Seeds of one plan and ST-KNN cases differ only in training options, which a file does not embed: another
    seed's file in a run's folder passed every check and was reported as the run's codec point. The file records
    the digest of the PLY it was compressed from (`stgc compress`), compared with the run's saved model."""
    from stgc.codec import model_digest

    seed0, seed1 = _run(tmp_path / "stg"), tmp_path / "stg-seed1"
    _write_ply(seed1 / "point_cloud" / "iteration_10" / "point_cloud.ply", rows=8)
    own, other = model_digest(seed0), model_digest(seed1)
    assert own != other and len(own) == 16
    copied = _bitstream(seed0 / "model_q3.stgc", _embedded(CONFIG), source_digest=other)
    record = _score(copied)
    assert "compressed from another model than the run's of iteration 10" in record["foreign"]
    assert record.get("training_finished") is None and record["train_seconds"] is None
    assert [row.extra.get("bitstream") for row in rows_from_run(seed0)] == [None]
    # Its own file, and one of an iteration the run did not keep (nothing to compare), are the run's.
    for name, iteration in (("own.stgc", 10), ("earlier.stgc", 5)):
        record = _score(_bitstream(seed0 / name, _embedded(CONFIG), iteration, source_digest=own if iteration == 10
                                   else other))
        assert "foreign" not in record, name
    # A folder without a config (an official run's) is told apart by the digest alone.
    official = tmp_path / "official"
    _write_ply(official / "point_cloud" / "iteration_10" / "point_cloud.ply", rows=9)
    record = _score(_bitstream(official / "model_q3.stgc", None, source_digest=other))
    assert "compressed from another model" in record["foreign"]
    # A run restored from a file holds the decoded model, not the PLY the file was compressed from.
    restored = tmp_path / "restored"
    _write_ply(restored / "point_cloud" / "iteration_10" / "point_cloud.ply", rows=20)
    (restored / "config.json").write_text(json.dumps(CONFIG))
    (restored / "restored_from.json").write_text(json.dumps({"bitstream": str(copied), "iteration": 10}))
    shutil.copy(copied, restored / "model_q3.stgc")
    assert "foreign" not in _score(restored / "model_q3.stgc")


def test_a_segments_file_without_its_run_config_in_the_whole_videos_folder_is_refused(tmp_path: Path) -> None:
    """The folder's config is the whole video's: a segment's model was scored at the video's times, on every frame."""
    from stgc.eval.evaluate import open_run_dataset
    from stgc.run import Run

    video = tmp_path / "video"
    Run(video).write_video({"segment_frames": 1, "data_path": str(tmp_path),
                            "segments": [{"name": f"segment_{k:03d}", "start": k, "duration": 1} for k in (0, 1)]})
    (video / "config.json").write_text(json.dumps(CONFIG))
    bare = _bitstream(video / "seg1.stgc", None)
    with pytest.raises(DataError, match="without its run config .* which segment's frames it covers is unknown"):
        open_run_dataset(video, None, bare)
    with pytest.raises(DataError, match="which segment's frames"):
        _score_real(bare)


def _score_real(target: Path) -> dict[str, Any]:
    return evaluate_run(target, load_model=lambda p: Model(), measure_fps=False)


def test_a_whole_video_bitstream_is_the_videos_only_where_each_segment_is_its_segment_runs(tmp_path: Path) -> None:
    from stgc.codec.format import encode
    from stgc.codec.synthetic import synthetic_model
    from stgc.codec.video import encode_video, read_video_index
    from stgc.eval.evaluate import foreign_video
    from stgc.run import Run

    video = tmp_path / "video"
    Run(video).write_video({"segment_frames": 1, "data_path": str(tmp_path),
                            "segments": [{"name": f"segment_{k:03d}", "start": k, "duration": 1} for k in (0, 1)]})
    configs = []
    for k in (0, 1):
        config = {**CONFIG, "data": {**CONFIG["data"], "start": k, "duration": 1}}
        (video / f"segment_{k:03d}").mkdir()
        (video / f"segment_{k:03d}" / "config.json").write_text(json.dumps(config))
        configs.append(config)
    (video / "config.json").write_text(json.dumps(CONFIG))
    arrays, _ = synthetic_model(20, "lite", seed=1)

    def container(path: Path, segment_configs: list[dict[str, Any]]) -> Path:
        path.write_bytes(encode_video([(k, 1, encode(arrays, "lite", None, 2, metadata={"run_config": _embedded(c)}))
                                       for k, c in enumerate(segment_configs)]))
        return path

    own = container(video / "model_q2.stgc", configs)
    assert foreign_video(own, read_video_index(own)) is None
    other = [configs[0], {**configs[1], "model": {"variant": "full"}}]
    copied = container(video / "copy.stgc", other)
    assert "segment 1: model.variant" in str(foreign_video(copied, read_video_index(copied)))
    single = tmp_path / "single"
    single.mkdir()
    (single / "config.json").write_text(json.dumps(CONFIG))
    shutil.copy(own, single / "v.stgc")
    assert "single model's run" in str(foreign_video(single / "v.stgc", read_video_index(own)))


# ------------------------------------------------------------------------------ test sets in reports


def _row(name: str, family: str, mbps: float, psnr: float, **test_set: Any) -> ReportRow:
    return ReportRow.from_mapping({"name": name, "family": family, "mbps": mbps, "psnr": psnr, **test_set})


A = {"data": "/data/scene", "cameras": ["0"], "frames": [0, 1, 2, 3], "downscale": 1.0}


def test_rows_of_different_test_sets_make_no_curve_and_no_comparison_together(tmp_path: Path) -> None:
    """Runs scored on other held-out cameras, frames, downscale or data were one RD curve, with BD deltas and
    "Rate vs ref." between PSNRs of different images, and no word about it."""
    base = [_row(f"b{i}", "STG", m, p, **A) for i, (m, p) in enumerate([(1.0, 30.0), (2.0, 32.0), (4.0, 34.0)])]
    same = [_row(f"s{i}", "codec", m, p, **A) for i, (m, p) in enumerate([(0.8, 30.0), (1.6, 32.0), (3.2, 34.0)])]
    for change in ({"cameras": ["3"]}, {"frames": [0, 1]}, {"downscale": 2.0}, {"data": "/data/other"}):
        other = {**A, **change}
        mixed = [_row("b9", "STG", 8.0, 36.0, **other),
                 *[_row(f"t{i}", "codec", m * 0.5, p, **other) for i, (m, p) in enumerate([(1.0, 30.0), (2.0, 32.0)])]]
        report = make_report(base + same + mixed, tmp_path / "r", baseline="STG")
        families = {r.family for r in report.rows}
        assert families == {"STG", "codec", "STG [test set B]", "codec [test set B]"}, change
        bd = {b.family: b for b in report.bd}
        assert bd["codec"].bd_rate == pytest.approx(-20.0, abs=1e-6)  # one test set's curves: compared
        for family in ("STG [test set B]", "codec [test set B]"):
            assert bd[family].bd_rate is None and bd[family].bd_psnr is None
            assert "another test set" in bd[family].note
        md = report.markdown.read_text()
        assert "2 different test sets" in md and "Test set B:" in md
        # The reference (the baseline's best point, 4 Mbps) is on test set A: rows of B get no change against it.
        assert "| STG [test set B] | b9 | rp01 | – | – | 8.00 | 36.00 | – | – | – |" in md
        assert "| codec | s0 | rp01 | – | – | 0.80 | 30.00 | – | -80.0 % | -4.00 |" in md
        assert set(json.loads(report.json_path.read_text())["test_sets"]) == {"A", "B"}
    # Rows that do not name their test set (given directly, or records written before they did) join any.
    plain = make_report([_row("x", "STG", 1.0, 30.0), *base], tmp_path / "plain", baseline="STG")
    assert {r.family for r in plain.rows} == {"STG"} and "test set" not in plain.markdown.read_text()
    # A data folder that is gone (moved since) is the same data as one of its name; one of another name is not.
    here = tmp_path / "now" / "scene"
    here.mkdir(parents=True)
    gone = {**A, "data": str(tmp_path / "before" / "scene")}
    for now, sets in ((here, {"STG"}), (tmp_path / "now", {"STG", "STG [test set B]"})):
        rows = [_row("a", "STG", 1.0, 30.0, **gone), _row("b", "STG", 2.0, 32.0, **{**A, "data": str(now)})]
        assert {r.family for r in make_report(rows, tmp_path / "moved").rows} == sets


def test_rate_points_number_each_test_sets_curve_on_its_own() -> None:
    """The experiment runner numbers its results.csv rate points with rate_points over its rows."""
    rows = [_row("a", "STG", 1.0, 30.0, **A), _row("b", "STG", 2.0, 32.0, **A),
            _row("c", "STG", 0.5, 31.0, **{**A, "frames": [0, 1]})]
    names = rate_points(rows)
    assert [names.get(id(r)) for r in rows] == ["rp01", "rp02", "rp01"]


def test_runs_on_different_test_sets_are_split_in_stgc_report(tmp_path: Path) -> None:
    """What the records of two runs say (cameras, frames), and their configs where the records do not (the data, the
    downscale of records the trainer wrote before they named them)."""
    scene, other = tmp_path / "scene", tmp_path / "other"
    scene.mkdir()
    other.mkdir()

    def run(name: str, data: Path, record: dict[str, Any], downscale: float = 1.0) -> Path:
        folder = tmp_path / name
        folder.mkdir()
        (folder / "config.json").write_text(json.dumps({"data": {"path": str(data), "downscale": downscale},
                                                        "compaction": {"method": "none"}}))
        (folder / "experiment.json").write_text(json.dumps({"family": "STG", "label": name}))
        (folder / "eval.json").write_text(json.dumps({"psnr": 30.0, "mbps": 10.0, "cameras": ["0"],
                                                      "frames": [0, 1], **record}))
        return folder

    a = run("a", scene, {})
    runs = [a, run("b", scene, {"psnr": 31.0, "mbps": 20.0})]
    assert {r.family for r in report_from_runs(runs, tmp_path / "r0").rows} == {"STG"}
    for name, extra in (("cams", ({}, {"cameras": ["3"]})), ("frames", ({}, {"frames": [0, 1, 2, 3]})),
                        ("data", (other, {})), ("down", ({"downscale": 2.0}, {}))):
        data = extra[0] if isinstance(extra[0], Path) else scene
        downscale = extra[0].get("downscale", 1.0) if isinstance(extra[0], dict) else 1.0
        report = report_from_runs([a, run(name, data, extra[1], downscale)], tmp_path / f"r_{name}")
        assert {r.family for r in report.rows} == {"STG", "STG [test set B]"}, name


def test_a_whole_videos_record_names_its_test_set() -> None:
    from stgc.eval.evaluate import aggregate_video_records

    segments = [(f"segment_{k}", {"psnr": 30.0, "num_views": 2, "duration_s": 1.0, "size_bytes": 10,
                                  "cameras": ["0"], "frames": [2 * k, 2 * k + 1], "data": "/d/scene", "downscale": 1.0,
                                  "per_camera": {"0": {"psnr": 30.0, "views": 2}}}) for k in (0, 1)]
    video = aggregate_video_records(segments)
    assert (video["cameras"], video["frames"], video["data"], video["downscale"]) == (["0"], [0, 1, 2, 3], "/d/scene",
                                                                                     1.0)


def test_a_trained_runs_own_bitstream_is_attributed_to_it_end_to_end(tmp_path: Path) -> None:
    """`stgc compress RUN --out RUN/model_q3.stgc`, then `stgc eval`: the config the encoder embeds is the run's
    config.json as the trainer wrote it, and compares equal to it; a copy in another run's folder does not."""
    from scenes import write_panoptic_scene

    from stgc.cli import main

    scene = write_panoptic_scene(tmp_path / "scene", views=5, frames=2, width=32, height=24)
    quick = ["--set", "train.iterations=4", "--set", "train.schedule_scale=1", "--set", "data.init_source=random",
             "--set", "data.max_points_per_frame=200", "--set", "train.progress=false",
             "--set", "train.tensorboard=false", "--set", "train.save_iterations=[4]"]
    run, other = tmp_path / "run", tmp_path / "other"
    assert main(["train", str(scene.root), "--out", str(run), *quick]) == 0
    assert main(["train", str(scene.root), "--out", str(other), *quick, "--set", "data.test_cameras=3"]) == 0
    for folder in (run, other):
        assert main(["compress", str(run), "--out", str(folder / "model_q3.stgc"),
                     "--set", "codec.allocation=ladder"]) == 0
        assert main(["eval", str(folder / "model_q3.stgc"), "--no-fps"]) == 0
    own = json.loads((run / "eval_model_q3.json").read_text())
    assert "foreign" not in own and own["training_finished"] is True
    assert [row.extra.get("bitstream") for row in rows_from_run(run)] == [None, "model_q3.stgc"]
    assert "data.test_cameras" in json.loads((other / "eval_model_q3.json").read_text())["foreign"]
    assert [row.extra.get("bitstream") for row in rows_from_run(other)] == [None]
    # The trainer's own record names its test set: the two runs' differ in their test camera.
    report = report_from_runs([run, other], tmp_path / "report")
    assert {r.family for r in report.rows} == {"STG", "STG + codec", "STG [test set B]"}
    # Another run's model copied in beside its decoder: it would load and score, into the run's eval.json.
    before = (run / "eval.json").read_text()
    for suffix in (".ply", ".pt"):
        shutil.copy(other / "point_cloud" / "iteration_4" / f"point_cloud{suffix}", run / f"other{suffix}")
    assert main(["eval", str(run / "other.ply"), "--no-fps"]) == 2
    assert (run / "eval.json").read_text() == before


def test_a_folder_inside_a_run_other_than_its_iterations_is_refused_too(tmp_path: Path) -> None:
    run = _run(tmp_path / "run")
    _write_ply(run / "copy" / "point_cloud.ply")
    with pytest.raises(DataError, match="not a saved model of the run"):
        _score(run / "copy")
    assert not (run / "copy" / "eval.json").exists()
    assert _score(run / "point_cloud" / "iteration_10")["num_gaussians"] == 7


def test_a_copy_of_a_bitstream_s_record_under_another_name_is_no_point_of_the_run(tmp_path: Path, caplog) -> None:
    """A saved `stgc eval RUN/model_q3.stgc --json` output (eval_q3.stdout.json) names the same .stgc: it was filed
    as a second point (rows twice, the rate-point labels on the copies)."""
    run = _run(tmp_path / "run")
    stgc = _bitstream(run / "model_q3.stgc", _embedded(CONFIG))
    _score(stgc)
    shutil.copy(run / "eval_model_q3.json", run / "eval_q3.stdout.json")
    with caplog.at_level("WARNING", logger="stgc"):
        rows = rows_from_run(run)
    assert [row.extra.get("bitstream") for row in rows] == [None, "model_q3.stgc"]
    assert any("eval_q3.stdout.json: left out" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize("section, value", [("compaction", "abc"), ("data", 5), ("train", [1])])
def test_a_damaged_config_is_named_not_a_traceback(tmp_path: Path, section: str, value: Any) -> None:
    from stgc.errors import FormatError

    run = _run(tmp_path / "run")
    (run / "config.json").write_text(json.dumps({**CONFIG, section: value}))
    with pytest.raises(FormatError, match=f"config.json: its '{section}' section is"):
        rows_from_run(run)
    config = {k: v for k, v in CONFIG.items() if k in ("data", "model")}  # a restored run's: what a file embeds
    assert rows_from_run(_run(tmp_path / "restored", config))
