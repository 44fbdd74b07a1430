"""A checkpoint is resumed only under the options it was trained with, and only by one trainer at a time.

An interrupted `stgc finetune` left NEW with its source's checkpoint and no config.json; `stgc train --resume` of NEW
then trained that checkpoint with the command line's defaults (thousands of iterations of another training). Two
trainers in one run folder (two resumes, or a resume beside a killed driver's Ray worker) wrote every metrics row
twice and interleaved their checkpoints.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from scenes import train_tiny_run, write_panoptic_scene

from stgc.cli import main
from stgc.errors import DataError
from stgc.options import configs_from_run
from stgc.run import Run


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_panoptic_scene(tmp_path_factory.mktemp("scene"), views=5, frames=2, width=32, height=24)


def _train(scene, run, *extra):
    return train_tiny_run(scene, run, "--set", "train.eval_at_end=false", *extra)


@pytest.fixture(scope="module")
def finished(scene, tmp_path_factory):
    run = tmp_path_factory.mktemp("runs") / "finished"
    assert _train(scene, run) == 0
    return run


@pytest.fixture(scope="module")
def stopped(scene, tmp_path_factory):
    """A run stopped at iteration 5 of 20, with its checkpoint: copy it before resuming it."""
    run = tmp_path_factory.mktemp("runs") / "stopped"
    assert _train(scene, run, "--set", "train.stop_after=5") == 0
    assert not Run(run).training_finished()
    return run


def _copy(run, tmp_path):
    copy = tmp_path / run.name
    shutil.copytree(run, copy)
    return copy


def _trainer(run, *, resume=True, **train_options):
    """A Trainer of `run` with the options its config.json saved (train options replaced by `train_options`)."""
    from stgc.train.loop import Trainer

    configs = configs_from_run(run)
    dataset = configs["data"].open(configs["data_path"])
    train_cfg = dataclasses.replace(configs["train"], **train_options)
    return Trainer(dataset, configs["data"], configs["model"], train_cfg, configs["compaction"], run, resume=resume)


# ------------------------------------------------------------------------------------ an interrupted fine-tuning
class Stopped(Exception):
    pass


def _start_continuation(source, new, *, stop_at_rename=None):
    """start_continuation of `source` into `new`, stopped as the `stop_at_rename`-th file renamed into place in
    `new` lands (None: not stopped); returns the names renamed into place, in order."""
    from stgc.train.continuation import continuation_configs, start_continuation

    renamed = []
    real_replace = os.replace

    def replace(src, dst, *args, **kwargs):
        if Path(dst).parent == new:
            renamed.append(Path(dst).name)
            if len(renamed) == stop_at_rename:
                raise Stopped
        return real_replace(src, dst, *args, **kwargs)

    configs = continuation_configs(configs_from_run(source), source, 2)
    os.replace = replace
    try:
        start_continuation(source, new, 2, configs)
    finally:
        os.replace = real_replace
    return renamed


def test_an_interrupted_finetune_leaves_no_checkpoint_without_its_config(finished, tmp_path):
    new = tmp_path / "new"
    order = _start_continuation(finished, new)
    # Every file is written whole, and the checkpoint last: after config.json and continued_from.json.
    assert order[-1] == Run.CHECKPOINT and {Run.CONFIG, Run.CONTINUED_FROM} <= set(order[:-1])
    shutil.rmtree(new)
    for stop in range(1, len(order) + 1):
        with pytest.raises(Stopped):
            _start_continuation(finished, new, stop_at_rename=stop)
        assert not (new / Run.CHECKPOINT).exists() or (new / Run.CONFIG).is_file(), stop
        # It removes what it wrote, so that the same command runs again.
        assert not [p.name for p in new.iterdir()], stop
    assert main(["finetune", str(finished), "--out", str(new), "--iterations", "2"]) == 0
    assert Run(new).training_finished() and Run(new).read_summary()["iterations"] == 22


def test_a_checkpoint_without_its_config_is_not_resumed_under_the_command_line_s_options(finished, scene, tmp_path,
                                                                                         capsys):
    """What the interrupted fine-tuning left (the source's checkpoint, no config.json): a resume with the command
    line's options (the cpu preset, 9,000 iterations) trained it as a run of its own."""
    new = tmp_path / "new"
    new.mkdir()
    shutil.copy2(finished / Run.CHECKPOINT, new / Run.CHECKPOINT)
    before = (new / Run.CHECKPOINT).read_bytes()
    capsys.readouterr()
    assert main(["train", str(scene.root), "--out", str(new), "--resume", "--set", "train.stop_after=1",
                 "--set", "train.progress=false", "--set", "train.tensorboard=false"]) == 2
    said = capsys.readouterr().err
    assert f"{new / Run.CHECKPOINT}: no {Run.CONFIG} beside it" in said and "Traceback" not in said
    assert (new / Run.CHECKPOINT).read_bytes() == before and not (new / Run.METRICS).exists()


# ------------------------------------------------------------------------------------ the checkpoint's options
def test_a_checkpoint_is_not_resumed_under_other_options(stopped, tmp_path, capsys):
    run = _copy(stopped, tmp_path)
    metrics = (run / Run.METRICS).read_text()
    with pytest.raises(DataError) as refused:
        _trainer(run, lambda_dssim=0.5, seed=7)
    message = str(refused.value)
    assert message.startswith(f"{run / Run.CHECKPOINT}: was trained with other options than this run's")
    assert "train.lambda_dssim: the checkpoint's 0.2, this run's 0.5" in message and "train.seed" in message
    assert (run / Run.METRICS).read_text() == metrics  # nothing truncated
    # The command line's resume takes config.json's options: an edited one is refused the same way.
    config = json.loads((run / Run.CONFIG).read_text())
    config["train"]["batch"] = 3
    (run / Run.CONFIG).write_text(json.dumps(config))
    capsys.readouterr()
    assert main(["train", "--out", str(run), "--resume"]) == 2
    said = capsys.readouterr().err
    assert f"{run / Run.CHECKPOINT}: was trained with other options" in said and "train.batch" in said
    assert (run / Run.METRICS).read_text() == metrics


def test_a_checkpoint_from_before_an_option_existed_resumes_as_it_trained(stopped, tmp_path):
    """A checkpoint whose recorded options lack one added since (compaction.removal_rate_max, session 40) trained as
    the option's SAVED_BEFORE says (0, not today's default 0.002): it resumes under a config.json that reads so, and
    is refused under another value of the option. (The run trains without compaction, where the option acts on
    nothing, so its recorded value can be taken out whatever it was.)"""
    from stgc.train.checkpoint import OPTIONS, OPTIONS_FINGERPRINT
    from stgc.train.loop import options_fingerprint

    run = _copy(stopped, tmp_path)
    checkpoint = torch.load(run / Run.CHECKPOINT, weights_only=False)
    assert checkpoint[OPTIONS].pop("compaction.removal_rate_max") == 0.002  # today's default
    checkpoint[OPTIONS_FINGERPRINT] = options_fingerprint(checkpoint[OPTIONS])
    torch.save(checkpoint, run / Run.CHECKPOINT)
    config = json.loads((run / Run.CONFIG).read_text())
    del config["compaction"]["removal_rate_max"]  # as the code of the day wrote it
    (run / Run.CONFIG).write_text(json.dumps(config))
    assert _trainer(run, checkpoint_every=0, progress=False).start_iteration == 5  # where `stopped` stopped
    from stgc.train.loop import Trainer

    configs = configs_from_run(run)
    capped = dataclasses.replace(configs["compaction"], removal_rate_max=0.5)
    with pytest.raises(DataError, match="compaction.removal_rate_max: the checkpoint's 0.0, this run's 0.5"):
        Trainer(configs["data"].open(configs["data_path"]), configs["data"], configs["model"], configs["train"],
                capped, run, resume=True)


def test_a_resume_that_changes_only_how_the_run_executes_is_accepted(stopped, tmp_path):
    run = _copy(stopped, tmp_path)
    threads = torch.get_num_threads()
    try:
        assert main(["train", "--out", str(run), "--resume", "--set", "train.threads=2", "--set", "train.stop_after=5",
                     "--set", "train.log_every=2", "--set", "train.backend=numba"]) == 0
        assert Run(run).read_summary() is None and Run(run).progress()[0] == 10
        trainer = _trainer(run, threads=1, checkpoint_every=0, progress=False)
        assert trainer.start_iteration == 10
        assert trainer.run()["finished"]
    finally:
        torch.set_num_threads(threads)
    sessions = Run(run).read_summary()["executions"]
    assert [(s["from_iteration"], s["threads"]) for s in sessions][1:] == [(5, 2), (10, 1)]


def test_a_checkpoint_written_before_its_options_were_recorded_still_resumes(stopped, tmp_path):
    from stgc.train.checkpoint import OPTIONS, OPTIONS_FINGERPRINT

    run = _copy(stopped, tmp_path)
    checkpoint = torch.load(run / Run.CHECKPOINT, weights_only=False)
    assert checkpoint.pop(OPTIONS_FINGERPRINT) and checkpoint.pop(OPTIONS)
    torch.save(checkpoint, run / Run.CHECKPOINT)
    assert main(["train", "--out", str(run), "--resume"]) == 0
    assert Run(run).training_finished()
    # A fine-tuning starts from its source's checkpoint, marked as trained with its own options.
    new = tmp_path / "new"
    assert main(["finetune", str(run), "--out", str(new), "--iterations", "3", "--set", "train.lambda_dssim=0.3"]) == 0
    assert Run(new).training_finished()


# ------------------------------------------------------------------------------------ one trainer per run folder
def _hold_lock(run):
    """A process that locks RUN/.lock as a trainer does (flock, its pid and host in the file) until its stdin
    closes."""
    code = ("import fcntl, json, os, socket, sys\n"
            "f = open(sys.argv[1], 'a+')\n"
            "fcntl.flock(f.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)\n"
            "f.seek(0); f.truncate(); f.write(json.dumps({'pid': os.getpid(), 'host': socket.gethostname()}))\n"
            "f.flush(); print('held', flush=True); sys.stdin.read()\n")
    holder = subprocess.Popen([sys.executable, "-c", code, str(run / ".lock")], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    return holder


def test_a_second_trainer_of_a_run_folder_is_refused_while_another_process_trains_it(stopped, finished, tmp_path,
                                                                                       capsys):
    run = _copy(stopped, tmp_path)
    metrics = (run / Run.METRICS).read_text()
    holder = _hold_lock(run)
    try:
        capsys.readouterr()
        assert main(["train", "--out", str(run), "--resume"]) == 2
        said = capsys.readouterr().err
        assert f"{run}: is being trained by another process (pid {holder.pid})" in said and "Traceback" not in said
        assert (run / Run.METRICS).read_text() == metrics
        # A fine-tuning is not started into it either.
        assert main(["finetune", str(finished), "--out", str(run), "--iterations", "2",
                     "--overwrite"]) == 2
        assert f"(pid {holder.pid})" in capsys.readouterr().err
        assert (run / Run.METRICS).read_text() == metrics and (run / Run.CONFIG).is_file()
    finally:
        holder.stdin.close()
        holder.wait(timeout=30)
    # Its holder gone, the folder is free (a killed holder's lock goes with it).
    assert main(["train", "--out", str(run), "--resume"]) == 0
    assert Run(run).training_finished()
    assert not (run / ".lock").exists()


def test_a_trainer_holds_its_run_folder_until_its_run_ends(stopped, tmp_path):
    from stgc.run import RunInUseError

    run = _copy(stopped, tmp_path)
    first = _trainer(run, stop_after=2)
    with pytest.raises(RunInUseError, match=rf"{run}: is being trained by another trainer of this process "
                                            rf"\(pid {os.getpid()};"):
        _trainer(run)
    first.run()
    assert not (run / ".lock").exists()

    def stop(iteration, numbers):
        raise Stopped

    second = _trainer(run)
    assert second.start_iteration == 7
    second.callback = stop
    with pytest.raises(Stopped):
        second.run()
    # Released on the way out of a failed run, and by a trainer dropped without running (once collected).
    _trainer(run)
    assert _trainer(run).run()["finished"]


def test_a_stale_lock_file_neither_blocks_nor_makes_a_run(scene, stopped, tmp_path):
    """A process killed while it trained leaves RUN/.lock behind (unlocked: the kernel released it)."""
    run = _copy(stopped, tmp_path)
    stale = json.dumps({"pid": 2 ** 22 + 1, "host": socket.gethostname()})
    (run / ".lock").write_text(stale)
    assert main(["train", "--out", str(run), "--resume"]) == 0 and Run(run).training_finished()
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    (fresh / ".lock").write_text(stale)
    assert _train(scene, fresh, "--set", "train.stop_after=1") == 0  # not "already holds a run"


# ------------------------------------------------------------------------------------ the data it trains on
def test_a_run_whose_data_folder_is_gone_continues_only_on_the_same_data(scene, stopped, finished, tmp_path,
                                                                          capsys):
    """Once the saved data folder is gone, DATA is taken for it (the data moved): the same views and images are
    accepted wherever they lie, another capture with the same cameras is refused, for a resume and a fine-tuning."""
    moved = tmp_path / "moved"
    shutil.copytree(scene.root, moved)
    other = write_panoptic_scene(tmp_path / "other", views=5, frames=2, width=32, height=24, seed=1)

    def gone(run):
        config = json.loads((run / Run.CONFIG).read_text())
        config["data"]["path"] = str(tmp_path / "gone")
        (run / Run.CONFIG).write_text(json.dumps(config))
        return run

    run = gone(_copy(stopped, tmp_path))
    metrics = (run / Run.METRICS).read_text()
    capsys.readouterr()
    assert main(["train", str(other.root), "--out", str(run), "--resume"]) == 2
    said = capsys.readouterr().err
    assert f"{other.root}: is not the data {run} trained on" in said
    assert (run / Run.METRICS).read_text() == metrics  # nothing truncated
    assert main(["train", str(moved), "--out", str(run), "--resume"]) == 0
    assert Run(run).training_finished()

    source = gone(_copy(finished, tmp_path / "sources"))
    new = tmp_path / "new"
    assert main(["finetune", str(source), "--data", str(other.root), "--out", str(new), "--iterations", "3"]) == 2
    assert f"{other.root}: is not the data {source} trained on" in capsys.readouterr().err
    assert not new.exists()
    assert main(["finetune", str(source), "--data", str(moved), "--out", str(new), "--iterations", "3"]) == 0
    assert Run(new).training_finished()
    # Its own folder, changed since: said as such.
    image = sorted((moved / "ims").rglob("*.png"))[0]
    image.write_bytes(image.read_bytes() + b"\0")
    capsys.readouterr()
    assert main(["finetune", str(new), "--out", str(tmp_path / "newer"), "--iterations", "3"]) == 2
    assert f"{moved}: changed since {new} started training on it" in capsys.readouterr().err


def test_the_data_fingerprint_names_the_views_images_and_masks_not_the_folder(tmp_path):
    from stgc.data import DataConfig

    scene = write_panoptic_scene(tmp_path / "a", views=4, frames=2, width=16, height=12, masks=True)
    first = DataConfig().open(scene.root)
    masks, images = sorted((scene.root / "seg").rglob("*.png")), sorted((scene.root / "ims").rglob("*.png"))
    assert masks and images and first.has_masks
    shutil.copytree(scene.root, tmp_path / "moved")
    assert DataConfig().open(tmp_path / "moved").fingerprint == first.fingerprint
    for changed in (masks[0], images[0]):
        copy = tmp_path / f"changed_{changed.parts[-3]}"
        shutil.copytree(scene.root, copy)
        target = copy / changed.relative_to(scene.root)
        target.write_bytes(target.read_bytes() + b"\0")  # another file, the same pixels where a reader ignores it
        assert DataConfig().open(copy).fingerprint != first.fingerprint, changed
