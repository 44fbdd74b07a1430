"""Run-level compression through stgc.model's checkpoint layout: compress_run, decompress, load_model, sizes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from stgc.codec import (
    CodecConfig,
    compress_run,
    decode,
    decompress,
    encode,
    load_model,
    model_digest,
    read_stgc,
    read_stgc_header,
    stgc_bytes_per_gaussian,
    stgc_file_bytes,
)
from stgc.codec.synthetic import synthetic_model
from stgc.errors import DataError, FormatError
from stgc.fileio import file_sha256
from stgc.model import STGModel


@pytest.fixture
def run_dir(tmp_path):
    arrays, decoder = synthetic_model(2000, "full", seed=4)
    model = STGModel.from_ply_arrays(arrays, "full", decoder, scene_extent=3.5, decoder_activation="clamp")
    run = tmp_path / "run"
    model.save(run / "point_cloud" / "iteration_500")
    model.save(run / "point_cloud" / "iteration_1200")
    config = {"data": {"path": "scene"}, "model": {"variant": "full", "decoder_activation": "clamp"}}
    (run / "config.json").write_text(json.dumps({**config, "train": {"iterations": 1200}}))
    return run, arrays, config  # what a restored run gets back: training options are not embedded


def test_compress_then_decompress_restores_an_equivalent_run(run_dir, tmp_path):
    run, arrays, config = run_dir
    result = compress_run(run, run / "model.stgc")
    # Gaussians whose temporal opacity stays below 1/255 for all t in [0, 1] are left out (written out here from
    # the STG formula: the peak is at t = trbf_center clamped to [0, 1]).
    gap = np.clip(arrays["trbf_center"], 0, 1) - arrays["trbf_center"]
    peak = np.exp(-((gap / np.exp(arrays["trbf_scale"])) ** 2)) / (1 + np.exp(-arrays["opacity"].astype(np.float64)))
    invisible = int(np.sum(peak < 1 / 255))
    assert invisible > 0  # the synthetic model has some: the test exercises the drop
    assert result.num_gaussians == 2000 - invisible and result.dropped_invisible == invisible
    assert result.variant == "full"
    assert result.file_bytes == stgc_file_bytes(run / "model.stgc") == (run / "model.stgc").stat().st_size
    assert result.ply_bytes == 2000 * 152 and result.ratio_vs_ply > 5  # against the input model's rows
    assert result.input_gaussians == 2000
    assert result.bytes_per_input_gaussian == pytest.approx(152 / result.ratio_vs_ply)
    assert stgc_bytes_per_gaussian(run / "model.stgc") == pytest.approx(result.file_bytes / result.num_gaussians)
    assert f"{result.file_bytes} bytes" in str(result) and "B per stored Gaussian" in str(result)
    assert f"{invisible} Gaussians left out" in str(result)
    assert read_stgc(run / "model.stgc").metadata["dropped_invisible"] == invisible
    # The model compressed, by its PLY's digest (stgc eval tells another run's file apart by it).
    assert read_stgc(run / "model.stgc").metadata["source_digest"] == model_digest(
        run / "point_cloud" / "iteration_1200" / "point_cloud.ply") == file_sha256(
        run / "point_cloud" / "iteration_1200" / "point_cloud.ply")[:16]
    kept = compress_run(run, tmp_path / "all.stgc", config=CodecConfig(drop_invisible=False))
    assert kept.num_gaussians == 2000 and kept.dropped_invisible == 0
    assert "dropped_invisible" not in read_stgc(tmp_path / "all.stgc").metadata
    # The options a file would not show are recorded where they are not the defaults (the runner checks them).
    assert "codec_options" not in read_stgc(run / "model.stgc").metadata
    assert read_stgc(tmp_path / "all.stgc").metadata["codec_options"] == {"drop_invisible": False}

    out = tmp_path / "restored"
    iteration_dir = decompress(run / "model.stgc", out)
    assert iteration_dir == out / "point_cloud" / "iteration_1200"  # the run's latest iteration
    assert json.loads((out / "config.json").read_text()) == config
    restored = STGModel.load(out)
    assert restored.decoder_activation == "clamp"  # from the restored config.json
    decoded = read_stgc(run / "model.stgc")
    for name, column in restored.to_ply_arrays().items():
        assert np.array_equal(column, decoded.arrays[name]), name


def test_load_model_gives_a_renderable_model_with_the_stored_activation(run_dir):
    run, _, _ = run_dir
    compress_run(run / "point_cloud" / "iteration_500" / "point_cloud.ply", run / "it500.stgc", quality=2,
                 config=CodecConfig(embed_run_config=False))
    model = load_model(run / "it500.stgc")
    assert isinstance(model, STGModel)
    assert (model.variant, model.decoder_activation) == ("full", "clamp") and model.num_gaussians <= 2000
    header = read_stgc_header(run / "it500.stgc")
    assert header.quality == 2
    assert decode(run / "it500.stgc").metadata["iteration"] == 500  # decode also takes a path
    assert "run_config" not in decode(run / "it500.stgc").metadata
    # Restored without its run's config, the run still renders with its decoder's activation (it was sigmoid).
    decompress(run / "it500.stgc", run.parent / "restored")
    assert STGModel.load(run.parent / "restored").decoder_activation == "clamp"
    # ... read from restored_from.json: a config.json holding only that would read its data options as defaults
    assert not (run.parent / "restored" / "config.json").exists()


def test_a_component_that_is_one_value_but_a_few_encodes_without_guard_bits(tmp_path):
    """The outlier guard's central range is 0 when >= 99.8 % of a component is one value: it overflowed to inf
    (a crash above a full range of 4) or added the full 8 bits (a decoded model's omega, mostly one code)."""
    from stgc.codec.format import outlier_guard_extra_bits

    values = np.zeros((4, 5000))
    for spread in (1.0, 3.0, 1e6):
        values[1, :3] = spread
        assert outlier_guard_extra_bits(values) == 0
    values[2] = np.linspace(0, 1, 5000)
    values[2, 0] = 1e300  # a tiny central spread against a huge one: at most the 8 bits, no overflow
    assert outlier_guard_extra_bits(values) == 8
    arrays, decoder = synthetic_model(1000, "full", seed=1)
    omega = [name for name in arrays if name.startswith("omega")]
    for name in omega:
        arrays[name][:] = 0.0
    arrays[omega[1]][:2] = 3.0
    decoded = decode(encode(arrays, "full", decoder, quality=3))
    column = decoded.arrays[omega[1]]
    assert np.count_nonzero(column) == 2 and np.all(np.abs(column[column != 0] - 3.0) < 0.5)  # the bulk exact


def test_only_a_lower_case_stgc_is_written_and_a_device_is_not_read(run_dir, tmp_path):
    run, _, _ = run_dir
    with pytest.raises(ValueError, match="lower case"):
        compress_run(run, tmp_path / "m.STGC")
    with pytest.raises(FormatError, match="not a regular file"):
        read_stgc("/dev/zero")


@pytest.mark.skipif(not Path("/proc/self/mem").is_file(), reason="needs Linux's /proc/self/mem")
def test_a_file_that_cannot_be_read_is_a_clear_error():
    # /proc/self/mem is a regular file of size 0 whose read fails (EIO): as a permission or disk error would.
    with pytest.raises(DataError, match="cannot read .stgc file"):
        read_stgc("/proc/self/mem")


def test_a_named_pipe_is_refused_unread_by_every_reader(tmp_path):
    """A .stgc path that is a pipe blocks whoever opens it until a writer comes: every reader refuses it unopened
    (`decompress` peeked at it for the video magic and hung). A watcher unblocks any reader that does open it and
    records that one did, so the test fails instead of hanging."""
    import os
    import threading

    from stgc.codec import decompress
    from stgc.codec.video import is_video_stgc, read_video_index

    fifo = tmp_path / "pipe.stgc"
    os.mkfifo(fifo)
    done, opened = threading.Event(), []

    def unblock_readers() -> None:
        while not done.is_set():
            try:  # succeeds only while a reader has the pipe open (blocked in open or read)
                fd = os.open(fifo, os.O_WRONLY | os.O_NONBLOCK)
            except OSError:
                done.wait(0.05)
                continue
            opened.append(True)
            os.close(fd)

    watcher = threading.Thread(target=unblock_readers, daemon=True)
    watcher.start()
    try:
        assert not is_video_stgc(fifo)
        for read in (read_stgc, read_video_index, lambda path: decompress(path, tmp_path / "out")):
            with pytest.raises(FormatError, match="not a regular file"):
                read(fifo)
    finally:
        done.set()
        watcher.join()
    assert not opened
    assert not (tmp_path / "out").exists()


def test_failures_leave_no_partial_output_and_name_the_file(run_dir, tmp_path):
    run, _, _ = run_dir
    with pytest.raises(ValueError, match="quality"):
        compress_run(run, tmp_path / "bad.stgc", quality=7)
    assert not (tmp_path / "bad.stgc").exists()
    assert list(tmp_path.glob(".bad.stgc*")) == []  # no temporary left behind
    broken = tmp_path / "broken.stgc"
    compress_run(run, broken)
    broken.write_bytes(broken.read_bytes()[:-10])
    with pytest.raises(FormatError, match="broken.stgc.*truncated"):
        decompress(broken, tmp_path / "never")
    assert not (tmp_path / "never").exists()
    with pytest.raises(DataError, match="cannot read"):
        read_stgc(tmp_path / "missing.stgc")


def test_a_bitstream_away_from_its_run_is_evaluated_on_the_dataset_its_embedded_config_names(run_dir, tmp_path):
    from stgc.eval import evaluate_run

    run, _, _ = run_dir
    away = tmp_path / "elsewhere"
    away.mkdir()
    compress_run(run, away / "with_config.stgc")
    # The embedded config names the dataset "scene" (absent here): the error proves it was the one looked up.
    with pytest.raises(DataError) as info:
        evaluate_run(away / "with_config.stgc", measure_fps=False)
    assert "scene" in str(info.value)
    compress_run(run, away / "bare.stgc", config=CodecConfig(embed_run_config=False))
    with pytest.raises(DataError, match="no run config found.*--data"):
        evaluate_run(away / "bare.stgc", measure_fps=False)


def test_a_whole_video_is_written_again_when_a_segment_measured_the_depths_its_window_trained(tmp_path):
    """The runner's check for codec points an earlier stgc wrote with measured depths looks into a whole-video
    container's segments: one segment whose run ended with a rate-aware window at the point's quality, stored
    without the window's depths, makes the container out of date; stored with them (or asked for explicitly), not."""
    from stgc.codec import CodecConfig
    from stgc.codec.files import WINDOW_MODE, written_without_window_depths
    from stgc.codec.format import encode
    from stgc.codec.video import encode_video
    from stgc.run import Run

    video = tmp_path / "video"
    Run(video).write_video({"segment_frames": 1, "data_path": str(tmp_path),
                            "segments": [{"name": f"segment_{k:03d}", "start": k, "duration": 1} for k in (0, 1)]})
    for k in (0, 1):
        segment = video / f"segment_{k:03d}"
        (segment / "point_cloud" / "iteration_10").mkdir(parents=True)
        (segment / "point_cloud" / "iteration_10" / "point_cloud.ply").write_bytes(b"")
        window = {"iterations": 10 * k, "quality": 2, "position_bits": 0, "allocation": "ladder", "simulate": True}
        (segment / "config.json").write_text(json.dumps({"train": {"quantization_aware": window}}))
        (segment / "train_summary.json").write_text(json.dumps({"finished": True, "iterations": 10,
                                                                "variant": "lite"}))
    arrays, _ = synthetic_model(20, "lite", seed=1)

    def container(second: dict) -> bytes:
        return encode_video([(0, 1, encode(arrays, "lite", None, 2, metadata={})),
                             (1, 1, encode(arrays, "lite", None, 2, metadata=second))])

    path = video / "model_q2.stgc"
    path.write_bytes(container({}))  # segment 1 trained through a window at q2, stored with measured depths
    q2, q3 = CodecConfig(quality=2), CodecConfig(quality=3)
    assert written_without_window_depths(path, q2) and not written_without_window_depths(path, q3)
    # compressed now with a measured allocation or the ladder, the file would not store the window's depths either
    assert not written_without_window_depths(path, CodecConfig(quality=2, allocation="optimised"))
    path.write_bytes(container({"allocation": {"mode": WINDOW_MODE, "quality": 2}}))
    assert not written_without_window_depths(path, q2)
    path.write_bytes(container({"allocation_option": "optimised"}))
    assert not written_without_window_depths(path, q2)


def test_a_run_restored_without_its_config_inside_another_run_is_its_own(run_dir, tmp_path):
    """A file written without its run's config, restored into a folder inside another run: evaluating or
    compressing the restored model took the outer run's config.json (its data, its decoder activation)."""
    from stgc.codec.files import read_stgc_metadata
    from stgc.eval import evaluate_run
    from stgc.run import Run

    run, _, _ = run_dir
    compress_run(run, tmp_path / "bare.stgc", config=CodecConfig(embed_run_config=False))
    model_dir = decompress(tmp_path / "bare.stgc", run / "restored")
    assert Run.of(model_dir) == Run(run / "restored")
    with pytest.raises(DataError, match="no run config found.*--data"):
        evaluate_run(model_dir, measure_fps=False)  # not the outer run's data, "scene"
    compress_run(model_dir, tmp_path / "again.stgc")
    assert "run_config" not in read_stgc_metadata(tmp_path / "again.stgc")


def test_a_bitstream_without_its_run_config_names_the_frames_it_is_scored_on(tmp_path, caplog):
    """A file written without its run config does not say which frames its model was trained on: opened on a
    dataset, the frames the default options give are named in the warning (a model of other frames would be
    scored on the wrong ones, and only the warning can say so)."""
    import logging

    from scenes import write_panoptic_scene

    from stgc.eval.evaluate import open_embedded_dataset

    scene = write_panoptic_scene(tmp_path / "scene", frames=3)
    with caplog.at_level(logging.WARNING, logger="stgc"):
        dataset = open_embedded_dataset({}, tmp_path / "bare.stgc", scene.root)
    assert dataset.frames == [0, 1, 2]
    assert "frames 0-2" in caplog.text and "embed_run_config" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="stgc"):
        segment = open_embedded_dataset({}, tmp_path / "bare.stgc", scene.root, frames=(1, 2))
    assert segment.frames == [1, 2] and "frames 1-2" in caplog.text


def test_compressing_a_run_without_a_saved_model_names_the_problem_only(tmp_path, capsys):
    """A run whose start saved its config and no model yet: one error, no warning about a model 'None'."""
    import json

    from stgc.cli import main

    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"data": {}, "model": {}, "train": {"iterations": 10}}))
    assert main(["compress", str(run), "--out", str(tmp_path / "m.stgc")]) == 2
    said = capsys.readouterr().err
    assert "None" not in said and "compressing its latest saved model" not in said and str(run) in said
