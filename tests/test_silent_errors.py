"""Cases that once gave a silently wrong result (issue #19), each driven through the command line as a user would.

Every test here failed on the code before the fix: it either wrote a wrong file or exited 0."""

from __future__ import annotations

import json
from dataclasses import replace
from types import SimpleNamespace

import pytest
from scenes import write_panoptic_scene

from stgc.cli import main


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_panoptic_scene(tmp_path_factory.mktemp("scene"), views=5, frames=2, width=32, height=24)


@pytest.fixture(scope="module")
def trained_run(scene, tmp_path_factory):
    run = tmp_path_factory.mktemp("runs") / "run"
    assert main(["train", str(scene.root), "--out", str(run), "--set", "train.iterations=10",
                 "--set", "train.schedule_scale=1", "--set", "data.init_source=random",
                 "--set", "train.progress=false", "--set", "train.tensorboard=false",
                 "--set", "train.save_iterations=[10]"]) == 0
    return run


def _train_args(scene, run, iterations="10", *extra):
    return ["train", str(scene.root), "--out", str(run), "--set", f"train.iterations={iterations}",
            "--set", "train.schedule_scale=1", "--set", "data.init_source=random", "--set", "train.progress=false",
            "--set", "train.tensorboard=false", "--set", f"train.save_iterations=[{iterations}]", *extra]


def test_training_into_an_existing_run_is_refused_and_overwrite_replaces_it(scene, trained_run, tmp_path, capsys):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(trained_run, run)
    (run / "notes.txt").write_text("mine")
    assert main(_train_args(scene, run, "12")) == 2
    assert "already holds a run" in capsys.readouterr().err
    assert (run / "point_cloud" / "iteration_10").is_dir()  # untouched
    (run / "model_q3.stgc").write_bytes(b"old bitstream")  # derived from the old model, with its evaluation
    (run / "eval_model_q3.json").write_text("{}")
    assert main(_train_args(scene, run, "12", "--overwrite")) == 0
    assert sorted(p.name for p in (run / "point_cloud").iterdir()) == ["iteration_12"]  # no stale model left
    assert not (run / "model_q3.stgc").exists() and not (run / "eval_model_q3.json").exists()
    assert (run / "notes.txt").read_text() == "mine"  # not a run file: kept


def test_eval_on_other_data_keeps_the_runs_own_record(scene, trained_run, tmp_path):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(trained_run, run)
    other = tmp_path / "other_scene"
    shutil.copytree(scene.root, other)
    own = json.loads((run / "eval.json").read_text())
    assert main(["eval", str(run), "--data", str(other), "--no-fps"]) == 0
    assert json.loads((run / "eval.json").read_text()) == own
    record = json.loads((run / "eval_on_other_scene.json").read_text())
    assert record["data"] == str(other.resolve())
    # Another dataset whose folder has the same name gets a record of its own, not the first one's overwritten.
    namesake = tmp_path / "elsewhere" / "other_scene"
    shutil.copytree(scene.root, namesake)
    assert main(["eval", str(run), "--data", str(namesake), "--no-fps"]) == 0
    assert json.loads((run / "eval_on_other_scene.json").read_text())["data"] == str(other.resolve())
    (second,) = [p for p in run.glob("eval_on_other_scene-*.json") if not p.name.endswith("_per_view.csv")]
    assert json.loads(second.read_text())["data"] == str(namesake.resolve())


@pytest.mark.parametrize("setting, field", [("train.iterations=0", "train.iterations"),
                                            ("train.iterations=-5", "train.iterations"),
                                            ("train.batch=0", "train.batch"),
                                            ("train.lr.opacity=nan", "train.lr.opacity"),
                                            ("data.near_plane=-1", "data.near_plane")])
def test_invalid_options_are_refused_before_anything_runs(setting, field, tmp_path, capsys):
    assert main(["train", "nowhere", "--out", str(tmp_path / "r"), "--set", setting]) == 2
    assert field in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("option", [["--time", "5"], ["--time", "-0.5"], ["--time", "nan"]])
def test_render_refuses_a_time_outside_the_model(trained_run, tmp_path, option, capsys):
    out = tmp_path / "still.png"
    assert main(["render", str(trained_run), "--out", str(out), *option]) == 2
    assert "outside the model's [0, 1]" in capsys.readouterr().err
    assert not out.exists()


def test_render_refuses_frames_outside_the_data(trained_run, tmp_path, capsys):
    out = tmp_path / "video.mp4"
    assert main(["render", str(trained_run), "--out", str(out), "--frames", "0:500"]) == 2
    assert "not within the dataset's frames" in capsys.readouterr().err
    assert not out.exists()


def test_compress_refuses_a_non_stgc_name_and_a_bad_allocation_at_once(trained_run, tmp_path, capsys):
    assert main(["compress", str(trained_run), "--out", str(tmp_path / "model.ply")]) == 2
    assert "must end in .stgc" in capsys.readouterr().err
    assert main(["compress", str(trained_run), "--out", str(tmp_path / "m.stgc"), "--codec.allocation", "bogus"]) == 2
    assert "codec.allocation: 'bogus' is not one of auto, trained, optimised, ladder" in capsys.readouterr().err
    # An option the chosen allocation never uses is refused, not ignored.
    for mode in ("ladder", "trained"):
        assert main(["compress", str(trained_run), "--out", str(tmp_path / "m.stgc"), "--set",
                     f"codec.allocation={mode}", "--set", "codec.allocation_views=4"]) == 2
        assert f"allocation {mode} renders no views" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_compress_takes_the_readmes_set_option(trained_run, tmp_path):
    out = tmp_path / "m.stgc"
    assert main(["compress", str(trained_run), "--out", str(out), "--set", "codec.allocation=ladder"]) == 0
    assert out.is_file()


def test_experiment_exits_non_zero_when_a_run_failed(monkeypatch, tmp_path, capsys):
    import stgc.cli

    monkeypatch.setattr(stgc.cli, "run_plan",
                        lambda *a, **k: SimpleNamespace(failed=["a", "b"], outcomes=["a", "b"]))
    assert main(["experiment", "scene", "--plan", "table2", "--out", str(tmp_path)]) == 1
    assert "2 of 2 runs failed" in capsys.readouterr().err


def test_out_whose_parent_is_a_file_is_a_clear_error(scene, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(_train_args(scene, blocker / "run")) == 2
    assert "is a file" in capsys.readouterr().err


def test_iterations_are_real_iterations_and_the_help_shows_the_presets(capsys):
    from stgc.options import resolve_configs
    from stgc.train.config import resolve_schedule

    configs = resolve_configs("cpu", {}, {"train": {"iterations": "300"}}, {})
    train = configs["train"]
    schedule = resolve_schedule(replace(train, densify=train.densify.resolved(sparse_cloud=False)))
    assert schedule.iterations == 300  # was 90: the number was scaled by the preset's 0.3
    assert schedule.densify_start == 150  # the schedule points still follow the preset's scale (500 x 0.3)
    with pytest.raises(SystemExit):
        main(["train", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "iterations to train (real iterations, not scaled) (default: 9000)" in help_text


def test_a_run_saved_with_iterations_in_schedule_units_resumes_with_its_real_count(trained_run, tmp_path):
    import shutil

    from stgc.options import configs_from_run

    run = tmp_path / "old"
    shutil.copytree(trained_run, run)
    saved = json.loads((run / "config.json").read_text())
    saved["train"].update(iterations=50, schedule_scale=0.2)  # the old meaning: 50 x 0.2 = 10 real iterations
    saved["train"]["resolved_schedule"]["iterations"] = 10
    (run / "config.json").write_text(json.dumps(saved))
    assert configs_from_run(run)["train"].iterations == 10


def test_a_truncated_image_is_found_by_inspect_decode_and_before_training(scene, tmp_path, capsys):
    import shutil

    root = tmp_path / "scene"
    shutil.copytree(scene.root, root)
    bad = root / "ims" / "2" / "000001.png"
    data = bad.read_bytes()
    bad.write_bytes(data[: int(len(data) * 0.6)])
    assert main(["data", "inspect", str(root)]) == 0  # the header alone looks fine
    capsys.readouterr()
    assert main(["data", "inspect", str(root), "--decode"]) == 2
    assert str(bad) in capsys.readouterr().err
    assert main(_train_args(scene, tmp_path / "run")[:1] + [str(root)] + _train_args(scene, tmp_path / "run")[2:]) == 2
    assert str(bad) in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_the_latest_iteration_is_one_rule_for_every_verb(trained_run, tmp_path):
    """An iteration folder without its PLY (a save that was interrupted) is not "the latest model" for anyone."""
    import shutil

    from stgc.codec.files import iteration_of
    from stgc.eval.accounting import latest_iteration_dir
    from stgc.model.ply import resolve_ply_path

    run = tmp_path / "run"
    shutil.copytree(trained_run, run)
    (run / "point_cloud" / "iteration_99").mkdir()  # empty: no point_cloud.ply
    assert latest_iteration_dir(run).name == "iteration_10"
    assert resolve_ply_path(run).parent.name == "iteration_10"
    assert iteration_of(run) == 10


def test_a_run_config_with_an_unknown_data_key_is_an_error_naming_the_file(trained_run, tmp_path, capsys):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(trained_run, run)
    saved = json.loads((run / "config.json").read_text())
    saved["data"]["downscal"] = 2  # a typo was dropped before: the run was evaluated at the wrong size
    (run / "config.json").write_text(json.dumps(saved))
    assert main(["eval", str(run), "--no-fps"]) == 2
    err = capsys.readouterr().err
    assert "config.json" in err and "downscal" in err


def test_a_run_saved_before_the_real_capture_options_resumes_as_it_trained(trained_run, tmp_path):
    import shutil

    from stgc.options import configs_from_run

    run = tmp_path / "old"
    shutil.copytree(trained_run, run)
    saved = json.loads((run / "config.json").read_text())
    for section, key in (("data", "near_plane"), ("data", "mask_points_per_frame"), ("model", "decoder_ray_origin"),
                         ("model", "decoder_ray_direction"), ("train", "colour_correction")):
        del saved[section][key]
    del saved["train"]["densify"]["stats_views"]
    del saved["train"]["densify"]["prune_in_rounds"]
    del saved["train"]["floaters"]["scale_min_opacity"]
    (run / "config.json").write_text(json.dumps(saved))
    configs = configs_from_run(run)
    assert configs["train"].floaters.scale_min_opacity == 0.0  # the scale rule took any opacity before the gate
    assert configs["data"].near_plane == 0.2 and configs["data"].mask_points_per_frame == 0
    assert configs["model"].decoder_ray_origin == "on" and configs["train"].colour_correction == "off"
    assert configs["model"].decoder_ray_direction == "on"
    assert configs["train"].densify.stats_views == "last"
    # Before the option, no round pruned (now None would mean "decide from the cloud": on for sparse clouds).
    assert configs["train"].densify.prune_in_rounds is False


def test_the_codec_allocation_measures_training_views_with_their_colour_correction(trained_run, tmp_path, monkeypatch):
    """A real rig's raw render of a training camera is off by that camera's tint; measured that way, part of the
    quantization error hides under it and the quality budget is looser than it says."""
    import shutil

    import numpy as np

    import stgc.codec.files as files
    import stgc.codec.views as views

    run = tmp_path / "run"
    shutil.copytree(trained_run, run)
    saved_path = run / "point_cloud" / "iteration_10" / "colour_correction.json"
    saved = json.loads(saved_path.read_text())
    assert saved["cameras"]  # the generated scene is a Panoptic layout: a real rig, so it was trained with one
    for entry in saved["cameras"].values():
        entry.update(gain=[2.0, 1.0, 0.5], offset=[0.0, 0.1, 0.0])
    saved_path.write_text(json.dumps(saved))
    renders = []

    def capture(arrays, variant, decoder_state, render, truth, budget, **kwargs):
        renders.append(render(arrays, decoder_state, range(len(truth))))
        raise RuntimeError("captured")

    monkeypatch.setattr(views, "optimise_allocation", capture)
    config = files.CodecConfig(allocation="optimised", allocation_views=3)
    for _ in range(2):
        with pytest.raises(RuntimeError, match="captured"):
            files.compress_run(run, tmp_path / "m.stgc", config=config)
        saved_path.unlink(missing_ok=True)  # the second time: a model trained without correction
    corrected, raw = np.stack(renders[0]), np.stack(renders[1])
    inside = (raw > 0) & (raw < 1)
    expected = np.clip(raw * np.array([2.0, 1.0, 0.5]) + np.array([0.0, 0.1, 0.0]), 0, 1)
    np.testing.assert_allclose(corrected[inside], expected[inside], atol=1e-6)
    assert inside.mean() > 0.5


def test_render_takes_a_bitstream_as_its_help_says(trained_run, tmp_path):
    stgc_file = tmp_path / "away" / "m.stgc"
    stgc_file.parent.mkdir()
    assert main(["compress", str(trained_run), "--out", str(stgc_file), "--set", "codec.allocation=ladder"]) == 0
    out = tmp_path / "still.png"
    assert main(["render", str(stgc_file), "--out", str(out)]) == 0  # the dataset from the embedded run config
    from PIL import Image

    assert Image.open(out).size == (32, 24)


def test_decompressing_into_an_existing_run_is_refused_unless_overwrite(trained_run, tmp_path, capsys):
    stgc_file = tmp_path / "m.stgc"
    assert main(["compress", str(trained_run), "--out", str(stgc_file), "--set", "codec.allocation=ladder"]) == 0
    target = tmp_path / "restored"
    assert main(["decompress", str(stgc_file), "--out", str(target)]) == 0
    (target / "point_cloud" / "iteration_99").mkdir()  # as if another run had lived here
    (target / "point_cloud" / "iteration_99" / "point_cloud.ply").write_text("old")
    assert main(["decompress", str(stgc_file), "--out", str(target)]) == 2
    assert "already holds a run" in capsys.readouterr().err
    assert main(["decompress", str(stgc_file), "--out", str(target), "--overwrite"]) == 0
    assert sorted(p.name for p in (target / "point_cloud").iterdir()) == ["iteration_10"]
    # Restoring into the folder that holds the bitstream: the old run's derived files go, the input stays.
    import shutil

    inside = target / "model_q3.stgc"
    shutil.copy(stgc_file, inside)
    (target / "eval_model_q3.json").write_text("{}")
    assert main(["decompress", str(inside), "--out", str(target), "--overwrite"]) == 0
    assert inside.is_file() and not (target / "eval_model_q3.json").exists()


def test_resuming_with_segment_frames_keeps_the_single_run(scene, trained_run, tmp_path, capsys):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(trained_run, run)
    before = sorted(p.relative_to(run) for p in run.rglob("*"))
    assert main(["train", "--out", str(run), "--resume", "--segment-frames", "1"]) == 2
    assert "single-segment run" in capsys.readouterr().err
    assert sorted(p.relative_to(run) for p in run.rglob("*")) == before  # nothing deleted


def test_resuming_names_the_same_data_however_spelled(scene, trained_run, tmp_path, monkeypatch):
    """The saved path, a relative path, a symlink, the metadata file in the folder, or a new place once the saved
    one is gone: each continues the run (the trainer is a stand-in that records the data it was handed)."""
    import shutil

    import stgc.cli

    calls = []
    monkeypatch.setattr(stgc.cli, "train", lambda dataset, *a, **k: calls.append(dataset.root))
    run = tmp_path / "run"
    shutil.copytree(trained_run, run)
    link = tmp_path / "link"
    link.symlink_to(scene.root)
    monkeypatch.chdir(scene.root.parent)
    for data in (str(scene.root), scene.root.name, str(link), str(scene.root / "train_meta.json")):
        assert main(["train", data, "--out", str(run), "--resume"]) == 0, data
    moved = tmp_path / "moved"
    shutil.copytree(scene.root, moved)
    config = json.loads((run / "config.json").read_text())
    config["data"]["path"] = str(tmp_path / "gone")
    (run / "config.json").write_text(json.dumps(config))
    assert main(["train", str(moved), "--out", str(run), "--resume"]) == 0
    assert len(calls) == 5


def test_resuming_on_other_data_is_refused(scene, trained_run, tmp_path, capsys):
    import shutil

    run, other = tmp_path / "run", tmp_path / "other_scene"
    shutil.copytree(trained_run, run)
    shutil.copytree(scene.root, other)
    assert main(["train", str(other), "--out", str(run), "--resume"]) == 2
    assert "not " + str(other) in capsys.readouterr().err
    assert main(["finetune", str(run), "--out", str(tmp_path / "tuned"), "--iterations", "2", "--data", str(other)]) == 2
    assert "not " + str(other) in capsys.readouterr().err
    assert not (tmp_path / "tuned").exists()


def test_resuming_with_another_preset_is_refused(trained_run, tmp_path, capsys):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(trained_run, run)
    assert main(["train", "--out", str(run), "--resume", "--preset", "paper"]) == 2
    assert "drop preset" in capsys.readouterr().err


@pytest.mark.parametrize("verb", [
    ["compress", "{run}", "--out", "{out}/m.stgc", "--set", "codec.allocation=ladder"],
    ["export", "{run}", "--format", "ply-frames", "--out", "{out}/frames"],
    ["render", "{run}", "--camera", "0", "--time", "0.5", "--out", "{out}/still.png"],
    ["report", "{run}", "--out", "{out}/report"],
    ["decompress", "{bitstream}", "--out", "{out}/restored"],
])
def test_an_output_that_cannot_be_written_is_a_clear_error_and_leaves_nothing(verb, trained_run, tmp_path, capsys):
    """A real limit, not a stand-in: RLIMIT_FSIZE makes every write past 512 bytes fail (EFBIG; Python ignores the
    SIGXFSZ it sends), as a full disk fails writes with ENOSPC; both are reported as the output's problem."""
    import resource

    bitstream = tmp_path / "in.stgc"
    assert main(["compress", str(trained_run), "--out", str(bitstream), "--set", "codec.allocation=ladder"]) == 0
    out = tmp_path / "out"
    out.mkdir()
    args = [a.format(run=trained_run, out=out, bitstream=bitstream) for a in verb]
    capsys.readouterr()
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (512, hard))
    try:
        code = main(args)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    err = capsys.readouterr().err
    assert code == 2, err
    assert "cannot write" in err and "Traceback" not in err
    leftovers = [p for p in out.rglob("*") if p.is_file() and (p.name.endswith(".tmp") or p.stat().st_size > 512)]
    assert leftovers == []


@pytest.mark.parametrize("code, words", [(28, "no space left"), (30, "read-only"), (13, "permission denied"),
                                         (32, "encoder writing it stopped")])  # ENOSPC, EROFS, EACCES, EPIPE
def test_output_errors_name_the_file_and_the_cause(tmp_path, monkeypatch, code, words):
    import os

    from stgc.errors import OutputError
    from stgc.fileio import write_json

    def failing_replace(src, dst):
        raise OSError(code, os.strerror(code), str(dst))

    monkeypatch.setattr("stgc.fileio.os.replace", failing_replace)
    target = tmp_path / "eval.json"
    with pytest.raises(OutputError, match=words) as info:
        write_json(target, {"a": 1})
    assert str(target) in str(info.value)
    assert list(tmp_path.iterdir()) == []  # the temporary file is gone too


def _per_view_frames(csv_path):
    import csv

    with open(csv_path, newline="") as f:
        return sorted({int(row["frame"]) for row in csv.DictReader(f)})


def test_a_run_keeps_its_frame_window_when_the_data_grows(tmp_path):
    root = tmp_path / "scene"
    write_panoptic_scene(root, views=5, frames=2, width=32, height=24)
    run = tmp_path / "run"
    assert main(_train_args(SimpleNamespace(root=root), run)) == 0
    saved = json.loads((run / "config.json").read_text())["data"]
    assert (saved["start"], saved["duration"]) == (0, 2)  # resolved, though no option set them
    write_panoptic_scene(root, views=5, frames=3, width=32, height=24)  # the capture's next frame, added later
    assert main(["eval", str(run), "--no-fps"]) == 0
    assert _per_view_frames(run / "eval_per_view.csv") == [0, 1]  # the frames it trained on, not the folder's


def test_a_bitstream_is_scored_on_its_own_frames_in_another_runs_folder(trained_run, tmp_path):
    # A segment's file written into its whole video's folder: the folder's config.json is not the file's run.
    stgc_file = tmp_path / "m.stgc"
    assert main(["compress", str(trained_run), "--out", str(stgc_file), "--set", "codec.allocation=ladder"]) == 0
    whole = tmp_path / "whole"
    whole.mkdir()
    config = json.loads((trained_run / "config.json").read_text())
    config["data"]["duration"] = 1
    (whole / "config.json").write_text(json.dumps(config))
    stgc_file.rename(whole / "m.stgc")
    assert main(["eval", str(whole / "m.stgc"), "--no-fps"]) == 0
    assert _per_view_frames(whole / "eval_m_per_view.csv") == [0, 1]


def test_an_evaluation_on_other_data_is_not_a_rate_point_of_the_report(scene, trained_run, tmp_path):
    import shutil

    from stgc.eval.report import rows_from_run

    run = tmp_path / "run"
    shutil.copytree(trained_run, run)
    other = tmp_path / "other_scene"
    shutil.copytree(scene.root, other)
    assert main(["compress", str(run), "--out", str(run / "model_q3.stgc"), "--set", "codec.allocation=ladder"]) == 0
    for target in (run, run / "model_q3.stgc"):
        assert main(["eval", str(target), "--no-fps"]) == 0
        assert main(["eval", str(target), "--data", str(other), "--no-fps"]) == 0
    assert {p.name for p in run.glob("eval*.json")} == {"eval.json", "eval_on_other_scene.json", "eval_model_q3.json",
                                                         "eval_model_q3_on_other_scene.json"}
    assert sorted(row.extra.get("bitstream", "") for row in rows_from_run(run)) == ["", "model_q3.stgc"]
    # Records written before they said so are told by the data folder they name.
    for path in run.glob("eval*_on_other_scene.json"):
        record = json.loads(path.read_text())
        del record["other_data"]
        path.write_text(json.dumps(record))
    assert sorted(row.extra.get("bitstream", "") for row in rows_from_run(run)) == ["", "model_q3.stgc"]



def test_bitstreams_whose_names_hold_a_dot_keep_their_own_evaluations(trained_run, tmp_path):
    import shutil

    run = tmp_path / "run"
    shutil.copytree(trained_run, run)
    for quality in ("5", "1"):
        stgc_file = run / f"model.q{quality}.stgc"
        assert main(["compress", str(run), "--out", str(stgc_file), "--quality", quality,
                     "--set", "codec.allocation=ladder"]) == 0
        assert main(["eval", str(stgc_file), "--no-fps"]) == 0
    records = {p.name: json.loads(p.read_text()) for p in run.glob("eval_model*.json")}
    assert set(records) == {"eval_model.q5.json", "eval_model.q1.json"}  # was one eval_model.json for both
    for quality in ("5", "1"):
        assert records[f"eval_model.q{quality}.json"]["size_bytes"] == (run / f"model.q{quality}.stgc").stat().st_size
        assert (run / f"eval_model.q{quality}_per_view.csv").is_file()


def test_a_bitstream_written_again_after_its_evaluation_is_not_reported_with_the_old_numbers(trained_run, tmp_path):
    import shutil

    from stgc.eval.report import rows_from_run
    from stgc.experiment.plans import RunSpec
    from stgc.experiment.runner import _codec_point

    run = tmp_path / "run"
    shutil.copytree(trained_run, run)
    stgc_file = run / "model_q5.stgc"
    assert main(["compress", str(run), "--out", str(stgc_file), "--quality", "5", "--set", "codec.allocation=ladder"]) == 0
    assert main(["eval", str(stgc_file), "--no-fps"]) == 0
    assert [row.extra.get("bitstream") for row in rows_from_run(run)] == [None, "model_q5.stgc"]
    # The same name written again (the runner's own allocation this time): the record on disk scored the earlier file.
    assert main(["compress", str(run), "--out", str(stgc_file), "--quality", "5"]) == 0
    assert [row.extra.get("bitstream") for row in rows_from_run(run)] == [None]
    # The experiment runner evaluates it again rather than reusing the stale record.
    commands = []

    def runner(cmd, log_path):
        commands.append(cmd)
        return main([*cmd[cmd.index("eval"):], "--no-fps"])

    spec = RunSpec(name="stg", overrides={}, family="STG", label="trained")
    outcome = _codec_point(spec, run, 5, runner, "python", tmp_path / "log.txt", lambda message: None, {})
    assert outcome.status == "finished" and len(commands) == 1 and "eval" in commands[0]
    assert outcome.record["size_bytes"] == stgc_file.stat().st_size
    assert [row.extra.get("bitstream") for row in rows_from_run(run)] == [None, "model_q5.stgc"]


def test_a_bitstream_is_filed_under_its_own_data_by_the_config_it_embeds(scene, trained_run, tmp_path):
    import shutil

    other = tmp_path / "other_scene"
    shutil.copytree(scene.root, other)
    folder = tmp_path / "folder"
    folder.mkdir()
    config = json.loads((trained_run / "config.json").read_text())
    config["data"]["path"] = str(other)  # the folder's run trained on other data than the file's
    (folder / "config.json").write_text(json.dumps(config))
    stgc_file = folder / "m.stgc"
    assert main(["compress", str(trained_run), "--out", str(stgc_file), "--set", "codec.allocation=ladder"]) == 0
    assert main(["eval", str(stgc_file), "--data", str(scene.root), "--no-fps"]) == 0  # the file's own data
    assert main(["eval", str(stgc_file), "--data", str(other), "--no-fps"]) == 0
    assert {p.name for p in folder.glob("eval_*.json")} == {"eval_m.json", "eval_m_on_other_scene.json"}
    assert not json.loads((folder / "eval_m.json").read_text()).get("other_data")

def _write_monocular(root, train_times, test_times, size=(20, 16)):
    """D-NeRF layout: one view per image, each with its own time (tests/data/test_formats.py has the format's test)."""
    import numpy as np
    from PIL import Image

    from stgc.data.cameras import w2c_to_opengl_c2w

    for split, times in (("train", train_times), ("test", test_times)):
        (root / split).mkdir(parents=True, exist_ok=True)
        frames = []
        for i, t in enumerate(times):
            image = np.full((size[1], size[0], 4), 80, np.uint8)
            image[..., 3] = 255
            column = int(2 + (size[0] - 6) * t)  # a block that moves with time
            image[4:12, column:column + 4, :3] = [220, 60, 30]
            Image.fromarray(image).save(root / split / f"r_{i:03d}.png")
            angle = 0.3 * i + (1.0 if split == "test" else 0.0)
            w2c = np.eye(4)
            w2c[:3, :3] = [[np.cos(angle), 0, -np.sin(angle)], [0, 1, 0], [np.sin(angle), 0, np.cos(angle)]]
            w2c[:3, 3] = [0, 0, 4]
            frames.append({"file_path": f"./{split}/r_{i:03d}", "time": float(t),
                           "transform_matrix": w2c_to_opengl_c2w(w2c).tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": frames}))
    return root


def test_monocular_images_are_rendered_at_the_time_their_file_names(tmp_path):
    from stgc.data import open_dataset

    # Test times between training times: their frames are ranks 1, 3 of 6 distinct times, which used to place
    # every image at rank / 6 instead of at its time.
    root = _write_monocular(tmp_path / "dnerf", [0.0, 0.25, 0.5, 1.0], [0.05, 0.3])
    data = open_dataset(root)
    assert data.frames == [0, 1, 2, 3, 4, 5] and data.train_frames == [0, 2, 4, 5]
    from stgc.data.points import initial_points
    from stgc.errors import DataError

    with pytest.raises(DataError, match=r"frames \[1\] have no training camera"):  # only a test image: no points
        initial_points(data, "random", frames=[0, 1])
    times = {c.name: c.time for c in data.train + data.test}
    scale = 5 / 6  # the last of 6 frames is at t = 5/6, as every frame-based format has it
    expected = {"train_r_000": 0.0, "test_r_000": 0.05, "train_r_001": 0.25, "test_r_001": 0.3, "train_r_002": 0.5,
                "train_r_003": 1.0}
    assert times == pytest.approx({name: t * scale for name, t in expected.items()})
    assert data.time_of(1) == pytest.approx(0.05 * scale)
    # Cut into segments, each segment's times stay in [0, 1) and keep the files' spacing (ranks 0-2 lie at times
    # 0, .05, .25; the next segment starts at .3).
    first, second = data.segment(0, 3), data.segment(3, 3)
    assert [first.time_of(f) for f in (0, 1, 2)] == pytest.approx([0, 0.05 / 0.3, 0.25 / 0.3])
    assert [second.time_of(f) for f in (3, 4, 5)] == pytest.approx([0, 0.2 / (0.7 * 3 / 2), 0.7 / (0.7 * 3 / 2)])
    # The viewer shows and scores a frame at the dataset's time, fractional frames in between.
    from stgc.viewer import Segment

    shown = Segment(model=None, dataset=data, frames=data.frames, size=None)  # type: ignore[arg-type]
    assert [shown.time_of(f) for f in data.frames] == pytest.approx([data.time_of(f) for f in data.frames])
    assert shown.time_of(1.5) == pytest.approx((data.time_of(1) + data.time_of(2)) / 2)
    # Evenly spaced times keep frame = rank exactly.
    even = open_dataset(_write_monocular(tmp_path / "even", [0.0, 0.5, 1.0], [0.25, 0.75]))
    assert [c.time for c in sorted(even.train + even.test, key=lambda c: c.frame)] == [0, 0.2, 0.4, 0.6, 0.8]


def test_monocular_training_never_draws_a_frame_only_a_test_image_holds(tmp_path):
    root = _write_monocular(tmp_path / "dnerf", [0.0, 0.25, 0.5, 0.75, 1.0], [0.1, 0.6])
    run = tmp_path / "run"
    # Every frame gets initial points (init_frames_every=1), and with init_source=auto: the frames that hold only a
    # test image used to give NaN colours ("non-finite rgb"), triangulation of one view, or a crash in the sampler.
    assert main(["train", str(root), "--out", str(run), "--set", "train.iterations=12", "--set",
                 "train.schedule_scale=1", "--set", "data.init_frames_every=1", "--set", "train.progress=false",
                 "--set", "train.tensorboard=false", "--set", "train.save_iterations=[12]"]) == 0
    assert json.loads((run / "eval.json").read_text())["num_views"] == 2



@pytest.mark.parametrize("options", [["--time", "0.5"], ["--orbit", "--camera", "0"], ["--orbit", "--frames", "0:1"]])
def test_render_refuses_video_options_it_would_ignore(trained_run, tmp_path, options, capsys):
    out = tmp_path / "v.mp4"
    assert main(["render", str(trained_run), "--out", str(out), *options]) == 2
    assert "v.mp4" in capsys.readouterr().err and not out.exists()


def test_a_saved_iteration_is_scored_with_its_runs_data_options(tmp_path):
    # Trained on frames 1-2 of 3 on white: the iteration folder's own evaluation must use that window and background,
    # with or without --data naming the run's data (it once opened the data with default options).
    root = tmp_path / "scene"
    write_panoptic_scene(root, views=5, frames=3, width=32, height=24)
    run = tmp_path / "run"
    assert main(_train_args(SimpleNamespace(root=root), run, "10", "--set", "data.start=1",
                            "--set", "data.duration=2", "--set", "data.background=white")) == 0
    assert main(["eval", str(run), "--no-fps"]) == 0
    whole = json.loads((run / "eval.json").read_text())
    iteration = run / "point_cloud" / "iteration_10"
    for extra in ([], ["--data", str(root)]):
        assert main(["eval", str(iteration), "--no-fps", *extra]) == 0
        record = json.loads((iteration / "eval.json").read_text())  # the run's own data: no _on_<name>
        assert record["frames"] == whole["frames"] == [1, 2]
        assert record["psnr"] == pytest.approx(whole["psnr"], abs=1e-9)
        assert record["duration_s"] == pytest.approx(whole["duration_s"])
        (iteration / "eval.json").unlink()


def test_a_case_or_criterion_alone_means_st_knn(scene, tmp_path):
    run = tmp_path / "run"
    assert main(_train_args(scene, run, "10", "--case", "2", "--criterion", "scale")) == 0
    compaction = json.loads((run / "config.json").read_text())["compaction"]
    assert (compaction["method"], compaction["case"], compaction["criterion"]) == ("st-knn", 2, "scale")
    assert (run / "compaction.jsonl").is_file()


@pytest.mark.parametrize("options", [["--compaction", "none", "--case", "2"], ["--set", "compaction.criterion=scale"],
                                     ["--compaction.case", "3"]])
def test_compaction_options_for_a_run_that_prunes_nothing_are_refused(scene, tmp_path, options, capsys):
    run = tmp_path / "run"
    assert main(_train_args(scene, run, "10", *options)) == 2
    assert "compaction.method is none" in capsys.readouterr().err and not run.exists()


@pytest.mark.parametrize("options, words", [
    (["--compaction", "st-knn", "--set", "compaction.window_start=0.1"], "window_start acts only with compaction.case=0"),
    (["--compaction", "st-knn", "--set", "compaction.ema_decay=0.9"], "ema_decay acts only with"),
    (["--compaction", "st-knn", "--set", "compaction.loss_smoothing=ema"],  # the default signal: prune_damage
     "loss_smoothing acts only with compaction.loss_signal=training"),
    (["--compaction", "st-knn", "--set", "compaction.loss_signal=probe", "--set", "compaction.loss_smoothing=ema"],
     "loss_smoothing acts only with compaction.loss_signal=training"),
    (["--compaction", "reference", "--set", "compaction.criterion=scale"],
     "criterion acts on nothing in a reference run"),
    (["--compaction", "st-knn", "--set", "compaction.loss_signal=training", "--set", "compaction.loss_budget_db=0",
      "--set", "compaction.probe_views=4"], "probe_views acts only with"),
    (["--compaction", "st-knn", "--set", "compaction.loss_signal=probe", "--set", "compaction.loss_budget_db=0",
      "--set", "compaction.ratio_increase=additive"], "ratio_increase acts only with compaction.loss_budget_db > 0"),
    # The paper's signal asked alone would keep the default damage budget, which is the probe signals'.
    (["--compaction", "st-knn", "--set", "compaction.loss_signal=training"],
     "loss_signal training compares the smoothed training loss step to step"),
    (["--variant", "lite", "--set", "model.decoder_activation=clamp"], "the lite model has no decoder"),
    (["--set", "train.quantization_aware.rate_weight=0.001"], "without a rate-aware window"),
    (["--train.quantization_aware.quality", "1"], "without a rate-aware window"),
    (["--set", "train.quantization_aware.iterations=5", "--set", "train.quantization_aware.rate_weight=0.001",
      "--set", "train.quantization_aware.remeasure_at_settle=false"], "acts only with train.quantization_aware.mask"),
    # The control (no simulated quantization) has no quality or depths; a run without a mask no mask learning rate.
    (["--set", "train.quantization_aware.iterations=5", "--set", "train.quantization_aware.simulate=false",
      "--set", "train.quantization_aware.quality=1"], "quality: acts only where the window simulates"),
    (["--set", "train.quantization_aware.iterations=5", "--set", "train.quantization_aware.rate_weight=0.001",
      "--set", "train.quantization_aware.mask_lr=0.1"], "mask_lr: acts only with train.quantization_aware.mask"),
])
def test_options_that_would_act_on_nothing_are_refused(scene, tmp_path, options, words, capsys):
    """A custom pruning window with a case's own window, EMA options with the windowed mean, rate-aware options
    without a window: recorded in config.json and changing nothing, the run would pass for what they name."""
    run = tmp_path / "run"
    assert main(_train_args(scene, run, "10", *options)) == 2
    assert words in capsys.readouterr().err and not run.exists()


def test_the_probe_size_of_a_reference_run_is_an_option_it_uses():
    """A reference run (method reference) probes as its pruned run does: probe_views acts there, loss_signal or not."""
    from stgc.compaction import CompactionConfig
    from stgc.options import refuse_unused_compaction_options

    refuse_unused_compaction_options(CompactionConfig(method="reference", probe_views=4), ["compaction.probe_views"])


def test_a_config_saved_without_compaction_is_read_as_no_compaction(tmp_path):
    """`train(..., compaction_cfg=None)` saves the section as null: read back, it is method none, not the default
    st-knn that a resume would then prune with."""
    from stgc.options import configs_from_run

    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"data": {"path": str(tmp_path)}, "model": {},
                                                 "train": {"iterations": 10}, "compaction": None}))
    assert configs_from_run(run)["compaction"].method == "none"


def test_preprocess_is_refused_with_a_plan_file(tmp_path):
    from stgc.config import ConfigError
    from stgc.experiment.plans import load_plan

    plan = tmp_path / "p.toml"
    plan.write_text('name = "p"\n[[runs]]\nname = "stg"\noverrides = { "compaction.method" = "none" }\n')
    assert load_plan(plan).runs[0].name == "stg"
    with pytest.raises(ConfigError, match="built-in plans"):
        load_plan(plan, "closest-pairs")


def test_an_evaluation_times_renders_with_the_threads_its_run_trained_with(scene, tmp_path):
    import torch

    from stgc import machine

    run = tmp_path / "run"
    assert main(_train_args(scene, run, "10", "--set", "train.threads=1")) == 0
    with machine.threads(2):  # what a fresh `stgc eval` process has on two cores
        assert main(["eval", str(run)]) == 0
        assert torch.get_num_threads() == 2  # given back after the evaluation
    speed = json.loads((run / "eval.json").read_text())["render_speed"]
    assert speed["threads"] == 1  # as the trainer's own evaluation timed it: FPS in one table compare


def test_lpips_is_computed_when_asked_or_the_record_says_why_not(trained_run, tmp_path):
    import shutil

    from stgc.metrics.image import lpips_status

    run = tmp_path / "run"
    shutil.copytree(trained_run, run)
    assert main(["eval", str(run), "--no-fps", "--lpips", "alex"]) == 0
    record = json.loads((run / "eval.json").read_text())
    available, reason = lpips_status("alex")
    if available:
        assert record["lpips"] is not None
    else:
        assert record["lpips"] is None and record["lpips_note"] == reason  # not "not requested"


def test_a_run_the_trainer_wrote_is_this_plans_run_however_its_data_is_named(scene, trained_run):
    # Every option of a real config.json against the plan's: nothing may differ for the very options it trained with,
    # whether DATA names the folder or its metadata file, and whatever its execution-only options were.
    from stgc.experiment.runner import reuse_mismatch

    options = {"train.iterations": "10", "train.schedule_scale": "1", "data.init_source": "random"}
    for data in (scene.root, scene.root / "train_meta.json"):
        assert reuse_mismatch(trained_run, data, "cpu", options) is None
    assert "train.iterations" in (reuse_mismatch(trained_run, scene.root, "cpu", {**options, "train.iterations": "12"})
                                  or "")


@pytest.mark.parametrize("options, words", [
    (["--set", "train.backend=gsplat"], "train.backend: backend 'gsplat' needs CUDA"),
    (["--set", "train.densify.max_growth=inf"], "max_growth"),
    (["--set", "data.triangulation_upsample=inf"], "triangulation_upsample"),
    (["--data.seed", "-1"], "data.seed"),
    (["--set", "train.floaters.until=-100"], "floaters.until"),
    (["--variant", "lite", "--model.variant", "full"], "model.variant: given twice, as lite"),
])
def test_options_that_fail_later_or_conflict_are_refused_before_the_run_folder(scene, tmp_path, options, words,
                                                                               capsys):
    """Each was accepted and then failed with a traceback after config.json was written (gsplat on the CPU, inf
    caps), went unchecked (a negative seed or iteration became another one), or was settled silently by a rule that
    differed between verbs (a shortcut flag and its option)."""
    run = tmp_path / "run"
    assert main(_train_args(scene, run, "10", *options)) == 2
    assert words in capsys.readouterr().err and not run.exists()


def test_resume_without_a_checkpoint_does_not_remove_a_decoded_or_official_model(scene, trained_run, tmp_path,
                                                                                 capsys):
    """--resume with nothing to resume restarted the run from scratch, which removed a model that `stgc
    decompress` restored (or an official run's point_cloud/): worse than no flag, which refuses the folder."""
    assert main(["compress", str(trained_run), "--out", str(tmp_path / "m.stgc"), "--quality", "1",
                 "--set", "codec.allocation=ladder"]) == 0
    assert main(["decompress", str(tmp_path / "m.stgc"), "--out", str(tmp_path / "restored")]) == 0
    before = sorted(p.relative_to(tmp_path) for p in (tmp_path / "restored").rglob("*"))
    assert main(["train", "--out", str(tmp_path / "restored"), "--resume"]) == 2
    assert "nothing to resume" in capsys.readouterr().err
    assert sorted(p.relative_to(tmp_path) for p in (tmp_path / "restored").rglob("*")) == before
    # Compressed again, it is measured without the colour correction the bitstream does not hold: said, not hidden.
    assert main(["compress", str(tmp_path / "restored"), "--out", str(tmp_path / "again.stgc"), "--quality", "1",
                 "--set", "codec.allocation_views=2"]) == 0
    assert "does not hold the training cameras' colour correction" in capsys.readouterr().err
    assert main(["compress", str(trained_run), "--out", str(tmp_path / "m.STGC")]) == 2
    assert "lower case" in capsys.readouterr().err


def test_resume_without_a_checkpoint_does_not_remove_a_finished_run(trained_run, tmp_path, capsys):
    """A finished run whose checkpoint was removed (to save space, or copied without it) was deleted, model,
    evaluation and bitstreams, and trained again from scratch."""
    import shutil

    run = tmp_path / "run"
    shutil.copytree(trained_run, run)
    (run / "checkpoint.pt").unlink()
    before = sorted(p.relative_to(run) for p in run.rglob("*"))
    assert main(["train", "--out", str(run), "--resume"]) == 2
    assert "nothing to resume" in capsys.readouterr().err
    assert sorted(p.relative_to(run) for p in run.rglob("*")) == before


def test_data_without_test_views_is_refused_before_training_when_the_run_evaluates(tmp_path, capsys):
    """It trained, then failed at its first evaluation with a generic message (before any checkpoint with
    eval_every)."""
    scene = write_panoptic_scene(tmp_path / "scene", views=4, frames=2, width=32, height=24, test_views=())
    run = tmp_path / "run"
    assert main(_train_args(scene, run, "10")) == 2
    assert "no test views to evaluate on" in capsys.readouterr().err and not run.exists()
    assert main(_train_args(scene, run, "10", "--set", "train.eval_at_end=false")) == 0


def test_eval_every_scores_the_last_iteration_when_the_end_of_run_evaluation_is_off(scene, tmp_path):
    run = tmp_path / "run"
    assert main(_train_args(scene, run, "10", "--set", "train.eval_every=5", "--set", "train.eval_at_end=false")) == 0
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in rows if "test_psnr" in r] == [5, 10]  # the final model was scored nowhere


def test_resume_in_a_folder_without_a_training_keeps_what_it_holds(scene, tmp_path, capsys):
    """--resume with nothing to resume overwrote like --overwrite: a bitstream, its evaluation and a TensorBoard
    folder in the folder were removed, where training into it without the flag keeps them. Files of a run that no
    training started (a foreign config.json) are refused, not taken for defaults and replaced."""
    folder = tmp_path / "folder"
    folder.mkdir()
    for name, text in (("model_q3.stgc", "x"), ("eval_model_q3.json", '{"psnr": 30}'), ("notes.txt", "hi")):
        (folder / name).write_text(text)
    assert main(_train_args(scene, folder, "4", "--resume")) == 0
    assert all((folder / name).is_file() for name in ("model_q3.stgc", "eval_model_q3.json", "notes.txt"))
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "config.json").write_text('{"comment": "not a stgc run"}')
    assert main(["train", str(scene.root), "--out", str(foreign), "--resume", "--set", "train.progress=false"]) == 2
    err = capsys.readouterr().err
    assert "nothing to resume" in err or "not a stgc run config" in err, err
    assert sorted(p.name for p in foreign.iterdir()) == ["config.json"]
    assert (foreign / "config.json").read_text() == '{"comment": "not a stgc run"}'


def test_a_start_killed_before_its_first_checkpoint_restarts_on_resume_even_with_a_saved_model(scene, tmp_path):
    """Its own partial state (a PLY saved before any checkpoint, checkpoint_every 0): a segment's retry resumes so."""
    run = tmp_path / "run"
    assert main(_train_args(scene, run, "10", "--set", "train.save_iterations=[4,10]", "--set",
                            "train.checkpoint_every=0", "--set", "train.stop_after=6")) == 0
    (run / "checkpoint.pt").unlink()  # as a kill before the first checkpoint
    assert (run / "point_cloud" / "iteration_4").is_dir()
    assert main(["train", "--out", str(run), "--resume"]) == 0
    assert json.loads((run / "train_summary.json").read_text())["finished"] is True


def test_a_run_restored_inside_another_runs_folder_keeps_its_own_decoder_activation(tmp_path):
    from stgc.codec import compress_run, decompress
    from stgc.codec.synthetic import synthetic_model
    from stgc.codec.files import CodecConfig
    from stgc.model import STGModel

    arrays, decoder = synthetic_model(300, "full", seed=2)
    outer = tmp_path / "outer"
    STGModel.from_ply_arrays(arrays, "full", decoder, decoder_activation="sigmoid").save(
        outer / "point_cloud" / "iteration_5")
    (outer / "config.json").write_text(json.dumps({"model": {"decoder_activation": "sigmoid"}}))
    bare = tmp_path / "bare" / "point_cloud" / "iteration_5"
    STGModel.from_ply_arrays(arrays, "full", decoder, decoder_activation="clamp").save(bare)
    (tmp_path / "bare" / "config.json").write_text(json.dumps({"model": {"decoder_activation": "clamp"}}))
    compress_run(bare / "point_cloud.ply", tmp_path / "m.stgc",
                 config=CodecConfig(allocation="ladder", embed_run_config=False))
    decompress(tmp_path / "m.stgc", outer / "restored")  # no embedded run config: no config.json of its own
    assert STGModel.load(outer / "restored").decoder_activation == "clamp"  # not the enclosing run's sigmoid
