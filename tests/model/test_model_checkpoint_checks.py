"""Checkpoint files that disagree with themselves or their run: damaged counts and configs, failed saves, the run a
decoder activation comes from."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from stgc.errors import FormatError
from stgc.model import STGModel
from stgc.run import official_run_args

from .helpers import random_model


def _official_run(root: Path, rgbfunction: str) -> Path:
    """An official STG run (cfg_args, no config.json) with a full model saved at iteration 25000."""
    random_model("full", count=4).save(root / "point_cloud" / "iteration_25000")
    (root / "cfg_args").write_text(f"Namespace(duration=50, rgbfunction='{rgbfunction}', loader='technicolor')")
    return root


def test_an_official_run_kept_inside_an_stgc_runs_folder_takes_its_own_decoder_activation(tmp_path):
    """The lookup climbed to the outer folder's config.json before it looked at any cfg_args: an official
    Technicolor run (a clamp) kept inside an N3DV run's folder (a sigmoid) rendered with the outer run's sigmoid."""
    (tmp_path / "config.json").write_text(json.dumps({"model": {"variant": "full", "decoder_activation": "sigmoid"}}))
    official = _official_run(tmp_path / "official_birthday", "sandwichnoact")
    assert STGModel.load(official).decoder_activation == "clamp"
    # And the other way round: an stgc run inside an official run's folder is its own.
    inner = tmp_path / "official_birthday" / "stgc_run"
    random_model("full", count=3).save(inner / "point_cloud" / "iteration_10")
    (inner / "config.json").write_text(json.dumps({"model": {"decoder_activation": "none"}}))
    assert STGModel.load(inner).decoder_activation == "none"


@pytest.mark.parametrize("marker", ["config", "cfg_args"])
def test_a_relative_path_finds_the_runs_decoder_activation(tmp_path, monkeypatch, marker):
    """Path('.').parents and Path('point_cloud.ply').parents are empty: loaded from inside the iteration dir, the
    run's config.json or cfg_args was never found and the model rendered with a sigmoid."""
    iteration = tmp_path / "point_cloud" / "iteration_30000"
    random_model("full", count=4).save(iteration)
    if marker == "config":
        (tmp_path / "config.json").write_text(json.dumps({"model": {"decoder_activation": "clamp"}}))
    else:
        (tmp_path / "cfg_args").write_text("Namespace(duration=50, rgbfunction='sandwichnoact')")
    monkeypatch.chdir(iteration)
    assert STGModel.load(".").decoder_activation == "clamp"
    assert STGModel.load("point_cloud.ply").decoder_activation == "clamp"
    monkeypatch.chdir(tmp_path / "point_cloud")
    assert STGModel.load("iteration_30000").decoder_activation == "clamp"
    if marker == "cfg_args":
        monkeypatch.chdir(iteration)
        assert official_run_args(".") == {"duration": 50, "rgbfunction": "sandwichnoact"}
        assert official_run_args("point_cloud.ply") == {"duration": 50, "rgbfunction": "sandwichnoact"}


def test_a_damaged_run_config_is_an_error_naming_it_not_a_sigmoid_guess(tmp_path):
    """A truncated config.json read as no config: the model loaded with a sigmoid decoder and a warning that named
    only the PLY."""
    random_model("full", count=4).save(tmp_path / "point_cloud" / "iteration_100")
    text = json.dumps({"model": {"variant": "full", "decoder_activation": "clamp"}})
    (tmp_path / "config.json").write_text(text[:-7])
    with pytest.raises(FormatError, match="cannot read JSON") as info:
        STGModel.load(tmp_path)
    assert str(tmp_path / "config.json") in str(info.value)
    (tmp_path / "config.json").unlink()
    (tmp_path / "restored_from.json").write_text('{"decoder_activation": "cla')
    with pytest.raises(FormatError, match="cannot read JSON") as info:
        STGModel.load(tmp_path)
    assert str(tmp_path / "restored_from.json") in str(info.value)


@pytest.mark.parametrize("broken", ["xyz", "decoder"])
def test_a_save_refused_for_non_finite_values_leaves_the_earlier_pair_intact(tmp_path, broken):
    """save() replaced point_cloud.pt before it checked the arrays: a model with a NaN parameter failed after the
    decoder was replaced, leaving the old PLY beside the new model's decoder (and a NaN decoder was saved, to fail
    only when loaded)."""
    iteration = tmp_path / "point_cloud" / "iteration_7000"
    earlier = random_model("full", count=5, seed=1)
    earlier.save(iteration)
    before = {name: (iteration / name).read_bytes() for name in ("point_cloud.ply", "point_cloud.pt")}
    later = random_model("full", count=5, seed=2)
    with torch.no_grad():
        if broken == "xyz":
            later.params["xyz"][0, 0] = float("nan")
        else:
            later.decoder.mlp2.weight[0, 0, 0, 0] = float("inf")
    name = "point_cloud.ply" if broken == "xyz" else "point_cloud.pt"
    with pytest.raises(FormatError, match="non-finite") as info:
        later.save(iteration)
    assert str(iteration / name) in str(info.value)
    assert {name: (iteration / name).read_bytes() for name in before} == before
    assert sorted(p.name for p in iteration.iterdir()) == ["point_cloud.ply", "point_cloud.pt"]  # no temporaries


def _rewrite_in_byte_order(path: Path, byte_order: str) -> None:
    vertex = PlyData.read(str(path), mmap=False)["vertex"]  # not mapped: the file is rewritten in place below
    PlyData([PlyElement.describe(vertex.data, "vertex")], byte_order=byte_order).write(str(path))


@pytest.mark.parametrize("byte_order", ["<", ">"])
def test_a_binary_ply_whose_header_count_disagrees_with_its_body_is_refused(tmp_path, byte_order):
    """plyfile reads the rows the header counts and ignores the rest: a header saying 40 vertices over a body of
    50 loaded the first 40 Gaussians without a word."""
    path = random_model("lite", count=50).save(tmp_path)
    _rewrite_in_byte_order(path, byte_order)
    raw = path.read_bytes()
    assert (b"format binary_big_endian" in raw) == (byte_order == ">")
    assert STGModel.load(path).num_gaussians == 50  # intact, in either byte order
    path.write_bytes(raw.replace(b"element vertex 50\n", b"element vertex 40\n", 1))
    with pytest.raises(FormatError, match="header counts 40 vertices but its body holds 50 ") as info:
        STGModel.load(path)
    assert str(path) in str(info.value)
    path.write_bytes(raw + b"\0" * 64)  # half a row of junk after the body
    with pytest.raises(FormatError, match=r"header counts 50 vertices but its body holds 50\.50 "):
        STGModel.load(path)
    path.write_bytes(raw.replace(b"element vertex 50\n", b"element vertex 60\n", 1))
    with pytest.raises(FormatError, match="header counts 60 vertices but its body holds only 50"):
        STGModel.load(path)


def test_a_decoder_saved_in_bfloat16_loads_and_one_of_no_numbers_is_a_format_error(tmp_path):
    """numpy has no bfloat16: a decoder saved in bfloat16 raised a bare TypeError; weights that are no numbers
    (strings) raised one from np.isfinite, naming no file."""
    model = random_model("full", count=3)
    path = model.save(tmp_path)
    decoder_path = tmp_path / "point_cloud.pt"
    state = {key: torch.as_tensor(value) for key, value in model.decoder_state().items()}
    torch.save({key: value.to(torch.bfloat16) for key, value in state.items()}, decoder_path)
    loaded = STGModel.load(path)
    for key, value in state.items():
        assert torch.equal(loaded.decoder.state_dict()[key], value.to(torch.bfloat16).float())
    for bad, shown in (([["w"] * 6] * 3, "<U1"), (state["mlp2.weight"].to(torch.complex64), "complex64")):
        torch.save({**state, "mlp2.weight": bad}, decoder_path)
        with pytest.raises(FormatError, match=f"'mlp2.weight' holds {shown} values, expected real numbers") as info:
            STGModel.load(path)
        assert str(decoder_path) in str(info.value)
    torch.save({**state, "mlp1.weight": [[0.0] * 12, [0.0] * 5]}, decoder_path)  # ragged: numpy cannot stack it
    with pytest.raises(FormatError, match="'mlp1.weight' is not an array of numbers"):
        STGModel.load(path)
