"""`stgc finetune RUN --out NEW --iterations N`: NEW starts as RUN's finished model and trains N more iterations
with only train.* options changed; RUN is left as it was."""

from __future__ import annotations

import hashlib
import json

import pytest
from scenes import train_tiny_run, write_panoptic_scene

from stgc.cli import main
from stgc.model import STGModel
from stgc.run import Run


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_panoptic_scene(tmp_path_factory.mktemp("scene"), views=5, frames=2, width=32, height=24)


def _train(scene, run, *extra):
    return train_tiny_run(scene, run, *extra)


@pytest.fixture(scope="module")
def source(scene, tmp_path_factory):
    run = tmp_path_factory.mktemp("runs") / "source"
    assert _train(scene, run, "--compaction", "st-knn") == 0
    return run


def _digest(run):
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(run.rglob("*")) if p.is_file()}


def test_finetune_continues_the_finished_model_with_new_train_options(source, tmp_path):
    before = _digest(source)
    start = STGModel.load(source)
    new = tmp_path / "new"
    assert main(["finetune", str(source), "--out", str(new), "--iterations", "10",
                 "--set", "train.quantization_aware.iterations=10",
                 "--set", "train.quantization_aware.allocation=ladder",
                 "--set", "train.quantization_aware.rate_weight=0.01"]) == 0
    assert _digest(source) == before  # the source run is untouched
    config = Run(new).read_config()
    assert config["train"]["iterations"] == 30 and config["train"]["quantization_aware"]["rate_weight"] == 0.01
    assert config["compaction"]["method"] == "none"  # the source's pruning is done, not re-opened
    assert config["data"] == Run(source).read_config()["data"] and config["model"] == Run(source).read_config()["model"]
    assert json.loads((new / Run.CONTINUED_FROM).read_text())["iteration"] == 20
    rows = [json.loads(line) for line in (new / Run.METRICS).read_text().splitlines()]
    iterations = [r["iteration"] for r in rows]
    assert iterations == sorted(iterations) and iterations[-1] == 30 and min(iterations) <= 5  # the whole history
    assert all(r.get("quantized") and "rate_bits" in r for r in rows if r["iteration"] > 20)
    assert Run(new).training_finished() and Run(new).read_eval() is not None
    # It started from the source's final model: the same Gaussians, moved a little by 10 iterations.
    final = STGModel.load(new)
    assert final.num_gaussians == start.num_gaussians and Run(new).latest_model_dir().name == "iteration_30"
    moved = (final.params["xyz"] - start.params["xyz"]).abs().max().item()
    assert 0 < moved < 0.05 * start.scene_extent


def test_finetune_refuses_what_it_cannot_honour(source, scene, tmp_path, capsys):
    def refused(*argv, expect):
        capsys.readouterr()
        assert main(["finetune", *argv]) == 2
        assert expect in capsys.readouterr().err

    refused(str(source), "--out", str(tmp_path / "a"), "--iterations", "5", "--set", "data.downscale=2",
            expect="data.downscale: a continuation changes train.* options only")
    refused(str(source), "--out", str(tmp_path / "b"), "--iterations", "5", "--set", "train.iterations=100",
            expect="train.iterations")
    refused(str(source), "--out", str(source), "--iterations", "5", expect="new run directory")
    refused(str(source), "--out", str(tmp_path / "c"), "--iterations", "0", expect="at least 1")
    refused(str(tmp_path / "nowhere"), "--out", str(tmp_path / "d"), "--iterations", "5", expect="not a run")
    unfinished = tmp_path / "unfinished"
    assert _train(scene, unfinished, "--set", "train.stop_after=10") == 0
    refused(str(unfinished), "--out", str(tmp_path / "e"), "--iterations", "5", expect="not finished")
    refused(str(source), "--out", str(tmp_path / "f"), "--iterations", "5", "--set",
            "train.quantization_aware.rate_weight=-1", expect="rate_weight")
    refused(str(source), "--out", str(tmp_path / "h"), "--iterations", "5", "--set",
            "train.quantization_aware.rate_weight=0.001", expect="without a rate-aware window")
    # A rate-aware window longer than the fine-tuning would start inside the source's finished training.
    refused(str(source), "--out", str(tmp_path / "g"), "--iterations", "5", "--set",
            "train.quantization_aware.iterations=6", expect="longer than the continuation's 5 iterations")
    # A mask window that error-guided sampling could edit (it left NEW written: the corrected command was refused).
    refused(str(source), "--out", str(tmp_path / "i"), "--iterations", "5", "--set",
            "train.quantization_aware.iterations=5", "--set", "train.quantization_aware.mask=true", "--set",
            "train.quantization_aware.rate_weight=0.001", "--set", "train.ems.enabled=true",
            expect="error-guided sampling (turn it off for the window")
    assert not any((tmp_path / x).exists() for x in "abcdfghi")  # nothing half-written


def test_finetune_refuses_what_the_trainer_would_before_new_is_written(source, scene, tmp_path, capsys):
    """The trainer's own checks (the backend, test views to score) came after NEW's checkpoint, config.json,
    continued_from.json and logs were written: the corrected command then found a run there."""
    new = tmp_path / "new"
    assert main(["finetune", str(source), "--out", str(new), "--iterations", "2",
                 "--set", "train.backend=gsplat"]) == 2
    assert "train.backend: backend 'gsplat' needs CUDA tensors" in capsys.readouterr().err
    assert not new.exists()
    assert main(["finetune", str(source), "--out", str(new), "--iterations", "2"]) == 0  # the corrected command
    # A source trained without evaluation on data without test views, continued with evaluation.
    untested = write_panoptic_scene(tmp_path / "untested", views=4, frames=2, width=24, height=16, test_views=())
    quiet = tmp_path / "quiet"
    assert _train(untested, quiet, "--set", "train.eval_at_end=false", "--set", "train.iterations=4") == 0
    assert main(["finetune", str(quiet), "--out", str(tmp_path / "scored"), "--iterations", "2",
                 "--set", "train.eval_at_end=true"]) == 2
    assert "no test views to evaluate on" in capsys.readouterr().err
    assert not (tmp_path / "scored").exists()


def test_finetune_refuses_options_that_act_on_nothing_and_a_preset_name(source, tmp_path, capsys):
    """The source trains without error-guided sampling and without clone/split: their options were recorded in
    NEW's config.json and ignored; train.preset named a schedule the run does not have."""
    for option, expect in (("train.ems.start=5", "train.ems.start: given for a run without error-guided sampling"),
                           ("train.densify.grad_threshold=1e-4", "train.densify.grad_threshold: acts only in "
                                                                 "clone/split rounds"),
                           ("train.preset=paper", "train.preset: set by the preset a run starts from")):
        assert main(["finetune", str(source), "--out", str(tmp_path / "new"), "--iterations", "2",
                     "--set", option]) == 2
        assert expect in capsys.readouterr().err
        assert not (tmp_path / "new").exists()


def test_a_killed_finetune_resumes_like_any_run(source, tmp_path, capsys):
    """stop_after is the command's that gave it: it was saved and stopped every resume again after as many
    iterations (a run stopped after 5 of 20 needed four resumes), and a fine-tuning of such a run inherited it."""
    new = tmp_path / "new"
    assert main(["finetune", str(source), "--out", str(new), "--iterations", "20",
                 "--set", "train.stop_after=5"]) == 0
    assert "stopped at iteration 25 of 40, unfinished" in capsys.readouterr().out
    assert not Run(new).training_finished()
    # Options of how it runs may be given to a resume (the others stay refused).
    assert main(["train", "--out", str(new), "--resume", "--set", "train.threads=1"]) == 0
    assert Run(new).training_finished() and Run(new).latest_model_dir().name == "iteration_40"
    # Each session's execution is kept (a loss reference's check reads them): the source's, the fine-tuning's
    # first 5 iterations, and the resume at 1 thread.
    sessions = (Run(new).read_summary() or {})["executions"]
    assert [s["from_iteration"] for s in sessions][-2:] == [20, 25] and sessions[-1]["threads"] == 1
    assert sessions[0]["from_iteration"] == 0 and len(sessions) == 3
    assert "run written to" in capsys.readouterr().out
    again = tmp_path / "again"
    assert main(["finetune", str(new), "--out", str(again), "--iterations", "3"]) == 0
    assert Run(again).training_finished()


def test_finetune_takes_its_own_colour_correction_learning_rate(source, tmp_path):
    import torch

    def colour_lr(run):
        state = torch.load(run / Run.CHECKPOINT, weights_only=False)["colour_correction"]
        return state["optimizer"]["param_groups"][0]["lr"]

    assert colour_lr(source) == pytest.approx(Run(source).read_config()["train"]["lr"]["colour_correction"])
    new = tmp_path / "new"
    # The checkpoint's optimizer state carried the source's rate, which silently won over the new option.
    assert main(["finetune", str(source), "--out", str(new), "--iterations", "4",
                 "--set", "train.lr.colour_correction=0.5"]) == 0
    assert colour_lr(new) == pytest.approx(0.5)


def test_a_window_opened_by_a_fine_tuning_takes_today_s_defaults_unless_its_source_had_one():
    """A source without a window read from an older config carries that version's window options (acting on
    nothing there): the fine-tuning's new window must not inherit them. A source that had a window passes its own
    options on, as a resumed window would."""
    from stgc.compaction import CompactionConfig
    from stgc.data import DataConfig
    from stgc.model import ModelConfig
    from stgc.train import TrainConfig
    from stgc.train.config import QuantizationAwareConfig
    from stgc.train.continuation import continuation_configs

    def source(window: QuantizationAwareConfig) -> dict:
        return {"data": DataConfig(), "model": ModelConfig(), "compaction": CompactionConfig(), "data_path": None,
                "train": TrainConfig(iterations=1000, quantization_aware=window)}

    opens = {"train.quantization_aware.iterations": "100", "train.quantization_aware.rate_weight": "1e-4",
             "train.quantization_aware.mask": "true"}
    old = source(QuantizationAwareConfig(remeasure_at_settle=False))  # how an older config.json reads
    assert continuation_configs(old, "SRC", 100, opens)["train"].quantization_aware.remeasure_at_settle
    windowed = source(QuantizationAwareConfig(iterations=50, rate_weight=1e-4, mask=True, remeasure_at_settle=False))
    again = continuation_configs(windowed, "SRC", 100, {"train.quantization_aware.iterations": "100"})
    assert not again["train"].quantization_aware.remeasure_at_settle and again["train"].quantization_aware.mask


def test_a_fine_tuning_of_a_budgeted_run_reads_back(source, tmp_path):
    """A fine-tuning carries its source's compaction section with method none: a source pruned against a loss
    reference left loss_reference in it, and the fine-tuning's config.json could not be read back (its resume, the
    runner's reuse check: 'compaction.loss_reference ... needs method st-knn')."""
    import shutil

    from stgc.options import configs_from_run

    run = tmp_path / "finetuned"
    shutil.copytree(source, run)
    config = json.loads((run / Run.CONFIG).read_text())
    config["compaction"].update(method="none", loss_reference=str(tmp_path / "reference"), loss_budget_db=0.3,
                                loss_signal="probe_psnr")
    (run / Run.CONFIG).write_text(json.dumps(config))
    assert configs_from_run(run)["compaction"].method == "none"
