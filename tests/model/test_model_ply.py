"""Official PLY checkpoints: bit-exact round trip, files written the way the official code writes them, validation."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement
from torch import nn

from stgc.errors import FormatError
from stgc.model import STGModel, bytes_per_gaussian, ply_fields

from .helpers import random_model


@pytest.mark.parametrize("variant", ["full", "lite"])
def test_save_load_round_trip_is_bit_exact(tmp_path, variant):
    model = random_model(variant, count=33)
    # values that a lossy path would disturb: negative zero, subnormals, extremes
    with torch.no_grad():
        model.params["xyz"][0] = torch.tensor([-0.0, 1e-40, 3.0e38])
        model.params["motion"][1, :3] = torch.tensor([np.nextafter(np.float32(1), np.float32(2)), -1e-30, 7.0])
    iteration_dir = tmp_path / "point_cloud" / "iteration_10"
    ply_path = model.save(iteration_dir)
    assert ply_path == iteration_dir / "point_cloud.ply"
    assert (iteration_dir / "point_cloud.pt").is_file() == (variant == "full")

    loaded = STGModel.load(ply_path)
    assert loaded.variant == variant and loaded.num_gaussians == 33
    for name, column in model.to_ply_arrays().items():
        assert column.dtype == np.float32
        assert loaded.to_ply_arrays()[name].tobytes() == column.tobytes(), name
    for key in model.params:
        assert model.params[key].detach().numpy().tobytes() == loaded.params[key].detach().numpy().tobytes()
    if variant == "full":
        for key, value in model.decoder_state().items():
            assert value.tobytes() == loaded.decoder_state()[key].tobytes()
            assert value.shape == {"mlp1.weight": (6, 12, 1, 1), "mlp2.weight": (3, 6, 1, 1)}[key]


@pytest.mark.parametrize("variant", ["full", "lite"])
def test_written_file_has_the_official_binary_layout(tmp_path, variant):
    model = random_model(variant, count=5)
    path = model.save(tmp_path)
    raw = path.read_bytes()
    header_end = raw.index(b"end_header\n") + len(b"end_header\n")
    header = raw[:header_end].decode("ascii").splitlines()
    assert header[1] == "format binary_little_endian 1.0"
    assert header[2] == "element vertex 5"
    assert header[3:-1] == [f"property float {name}" for name in ply_fields(variant)]
    assert len(raw) - header_end == 5 * bytes_per_gaussian(variant)
    body = np.frombuffer(raw[header_end:], dtype="<f4").reshape(5, -1)
    fields = ply_fields(variant)
    np.testing.assert_array_equal(body[:, fields.index("trbf_center")], model.params["trbf_center"][:, 0].detach())
    np.testing.assert_array_equal(body[:, fields.index("nx") : fields.index("nz") + 1], 0.0)


class _OfficialSandwich(nn.Module):
    def __init__(self):
        super().__init__()
        self.mlp1 = nn.Conv2d(12, 6, kernel_size=1, bias=False)
        self.mlp2 = nn.Conv2d(6, 3, kernel_size=1, bias=False)
        self.relu = nn.ReLU()
        self.sigmoid = nn.Sigmoid()


def _write_like_the_official_code(path: Path, columns: dict[str, np.ndarray], variant: str) -> None:
    """save_ply as the official GaussianModel does it: a structured array of 'f4' in construct_list_of_attributes
    order, written by plyfile with its defaults, and the decoder state_dict saved beside it with torch.save."""
    names = ply_fields(variant)
    count = len(columns["x"])
    elements = np.empty(count, dtype=[(name, "f4") for name in names])
    attributes = np.stack([columns.get(name, np.zeros(count, np.float32)) for name in names], axis=1)
    elements[:] = list(map(tuple, attributes))
    PlyData([PlyElement.describe(elements, "vertex")]).write(str(path))
    if variant == "full":
        torch.manual_seed(4)
        torch.save(_OfficialSandwich().state_dict(), str(path).replace(".ply", ".pt"))


@pytest.mark.parametrize("variant", ["full", "lite"])
def test_a_ply_written_like_the_official_code_loads(tmp_path, variant):
    rng = np.random.default_rng(0)
    columns = {name: rng.normal(size=7).astype(np.float32) for name in ply_fields(variant)}
    columns["rot_0"] = np.ones(7, np.float32)
    path = tmp_path / "point_cloud.ply"
    _write_like_the_official_code(path, columns, variant)

    model = STGModel.load(path)
    assert model.variant == variant and model.num_gaussians == 7
    np.testing.assert_array_equal(model.params["xyz"].detach().numpy(), np.stack([columns[c] for c in "xyz"], 1))
    np.testing.assert_array_equal(model.params["opacity"][:, 0].detach().numpy(), columns["opacity"])
    dc = [f"f_dc_{i}" for i in range(6 if variant == "full" else 3)]
    np.testing.assert_array_equal(model.params["features_dc"].detach().numpy(), np.stack([columns[c] for c in dc], 1))
    np.testing.assert_array_equal(model.params["motion"][:, 4].detach().numpy(), columns["motion_4"])
    if variant == "full":
        np.testing.assert_array_equal(model.params["features_t"][:, 2].detach().numpy(), columns["f_t_2"])
        official = torch.load(tmp_path / "point_cloud.pt")
        for key, value in official.items():
            np.testing.assert_array_equal(model.decoder_state()[key], value.numpy())


def test_load_resolves_run_and_iteration_dirs_and_reads_the_activation_from_the_run_config(tmp_path):
    early, late = random_model("full", count=4, seed=1), random_model("full", count=9, seed=2)
    early.save(tmp_path / "point_cloud" / "iteration_7")
    late.save(tmp_path / "point_cloud" / "iteration_30")
    (tmp_path / "point_cloud" / "iteration_100").mkdir()  # an interrupted save has no PLY: ignored
    (tmp_path / "config.json").write_text(json.dumps({"model": {"decoder_activation": "clamp"}}))
    from_run = STGModel.load(tmp_path)
    assert from_run.num_gaussians == 9 and from_run.decoder_activation == "clamp"
    assert STGModel.load(tmp_path / "point_cloud" / "iteration_7").num_gaussians == 4
    assert STGModel.load(tmp_path, decoder_activation="none").decoder_activation == "none"
    with pytest.raises(FormatError, match="no point_cloud.ply"):
        STGModel.load(tmp_path / "point_cloud" / "iteration_100")


def _rewrite(path: Path, drop: str | None = None, dtype_of: str | None = None, nan_in: str | None = None) -> None:
    vertex = PlyData.read(str(path))["vertex"]
    names = [p.name for p in vertex.properties if p.name != drop]
    rows = np.empty(vertex.count, dtype=[(n, "f8" if n == dtype_of else "f4") for n in names])
    for name in names:
        rows[name] = vertex[name]
    if nan_in:
        rows[nan_in][2] = np.nan
    PlyData([PlyElement.describe(rows, "vertex")]).write(str(path))


@pytest.mark.parametrize(
    "edit, message",
    [
        ({"drop": "omega_2"}, "missing field.*omega_2"),
        ({"dtype_of": "scale_1"}, "'scale_1' has dtype float64, expected float32"),
        ({"nan_in": "trbf_scale"}, "'trbf_scale' has 1 non-finite"),
    ],
)
def test_invalid_plys_raise_a_format_error_naming_the_file(tmp_path, edit, message):
    path = random_model("lite", count=5).save(tmp_path)
    _rewrite(path, **edit)
    with pytest.raises(FormatError, match=message) as info:
        STGModel.load(path)
    assert str(path) in str(info.value)


def test_missing_decoder_and_garbage_files_raise_format_errors(tmp_path):
    path = random_model("full", count=3).save(tmp_path)
    (tmp_path / "point_cloud.pt").unlink()
    with pytest.raises(FormatError, match="point_cloud.pt: missing"):
        STGModel.load(path)
    path.write_bytes(b"ply\nformat nonsense\n")
    with pytest.raises(FormatError, match="not a readable PLY"):
        STGModel.load(path)
    with pytest.raises(FormatError, match="no such file"):
        STGModel.load(tmp_path / "nowhere")


def test_from_ply_arrays_rejects_bad_arrays_and_round_trips_state_dict():
    model = random_model("full", count=4)
    arrays = model.to_ply_arrays()
    assert list(arrays) == ply_fields("full")
    rebuilt = STGModel.from_ply_arrays(arrays, "full", model.decoder_state(), scene_extent=2.0)
    assert rebuilt.scene_extent == 2.0
    with pytest.raises(FormatError, match="decoder_state"):
        STGModel.from_ply_arrays(arrays, "full", None)
    with pytest.raises(FormatError, match="float32"):
        STGModel.from_ply_arrays({**arrays, "x": arrays["x"].astype(np.float64)}, "full", model.decoder_state())
    again = STGModel.from_state_dict(model.state_dict())
    for key in model.params:
        assert torch.equal(again.params[key], model.params[key])


@pytest.mark.parametrize("rgbfunction, activation", [("sandwich", "sigmoid"), ("sandwichnoact", "clamp"),
                                                     ("sandwichnoactss", "none")])
def test_an_official_runs_decoder_ends_as_its_cfg_args_says(tmp_path, rgbfunction, activation):
    """An official run has no config.json; its rgbfunction is in RUN/cfg_args (the repr of its argparse Namespace).
    Technicolor's and the immersive configs' decoders were read as N3DV's sigmoid: 19 of the 25 official full
    configs rendered wrong colours."""
    random_model("full", count=4).save(tmp_path / "point_cloud" / "iteration_30000")
    (tmp_path / "cfg_args").write_text(f"Namespace(duration=50, model='ours_full', rgbfunction='{rgbfunction}', "
                                       f"save_iterations=[7000, 25000], loader='technicolor')")
    assert STGModel.load(tmp_path).decoder_activation == activation
    assert STGModel.load(tmp_path / "point_cloud" / "iteration_30000" / "point_cloud.ply").decoder_activation == activation


def test_an_unknown_official_decoder_or_none_said_is_not_taken_silently(tmp_path, caplog):
    random_model("full", count=4).save(tmp_path / "point_cloud" / "iteration_10")
    (tmp_path / "cfg_args").write_text("Namespace(rgbfunction='sandwichmlp', duration=50)")
    with pytest.raises(FormatError, match="rgbfunction='sandwichmlp' is not one stgc renders"):
        STGModel.load(tmp_path)
    (tmp_path / "cfg_args").write_text("import os")  # never executed
    with pytest.raises(FormatError, match="cfg_args: not an official STG cfg_args file"):
        STGModel.load(tmp_path)
    (tmp_path / "cfg_args").unlink()
    with caplog.at_level("WARNING"):
        assert STGModel.load(tmp_path).decoder_activation == "sigmoid"
    assert "sigmoid assumed" in caplog.text


def test_an_official_runs_data_opens_with_its_duration(tmp_path):
    """`stgc eval OFFICIAL_RUN --data SCENE`: the model's times are (frame - start) / duration with the run's own
    duration; opened with every frame of the folder, t was scaled by the wrong length."""
    from scenes import write_panoptic_scene

    from stgc.data.config import open_run_dataset

    scene = write_panoptic_scene(tmp_path / "scene", views=3, frames=4, width=16, height=12)
    run = tmp_path / "official"
    run.mkdir()
    assert open_run_dataset(run, scene.root).frames == [0, 1, 2, 3]
    (run / "cfg_args").write_text("Namespace(duration=2, rgbfunction='sandwich')")
    data = open_run_dataset(run, scene.root)
    assert data.frames == [0, 1] and [data.time_of(f) for f in data.frames] == [0.0, 0.5]


def test_decoder_weights_and_ply_fields_stgc_does_not_know_are_refused(tmp_path):
    model = random_model("full", count=3)
    path = model.save(tmp_path)
    state = {k: torch.as_tensor(v) for k, v in model.decoder_state().items()}
    for bad, message in (({**state, "mlp1.bias": torch.zeros(6)}, "key.*mlp1.bias"),
                         ({**state, "mlp1.weight": state["mlp1.weight"].reshape(12, 6, 1, 1)}, r"shape \(12, 6, 1, 1\)")):
        torch.save(bad, tmp_path / "point_cloud.pt")
        with pytest.raises(FormatError, match=message):
            STGModel.load(path)
    torch.save({k: v.reshape(v.shape[:2]) for k, v in state.items()}, tmp_path / "point_cloud.pt")  # [out, in]
    assert STGModel.load(path).num_gaussians == 3
    torch.save(state, tmp_path / "point_cloud.pt")
    vertex = PlyData.read(str(path))["vertex"]
    names = [p.name for p in vertex.properties] + ["f_dc_9"]
    rows = np.zeros(vertex.count, dtype=[(n, "f4") for n in names])
    for name in names[:-1]:
        rows[name] = vertex[name]
    PlyData([PlyElement.describe(rows, "vertex")]).write(str(path))
    with pytest.raises(FormatError, match="does not have: f_dc_9"):  # it would have rendered truncated
        STGModel.load(path)
    _rewrite(path, drop="f_dc_9")
    _rewrite(path, drop="f_t_1")
    with pytest.raises(FormatError, match="missing field.*f_t_1"):  # the list was empty
        STGModel.load(path)
