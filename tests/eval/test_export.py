"""`stgc export --format ply-frames`: static 3DGS per frame, read back with plyfile and rendered as a static splat."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from plyfile import PlyData
from scenes import moving_model, write_panoptic_scene

from stgc.cli import main
from stgc.data import open_dataset
from stgc.eval.export import (
    INRIA_FIELDS,
    SH_C0,
    export_ply_frames,
    gaussians_at,
    read_inria_ply,
    static_render_inputs,
    training_view_origin,
)
from stgc.metrics import psnr
from stgc.model import STGModel
from stgc.render import rasterize


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_panoptic_scene(tmp_path_factory.mktemp("export"), views=5, frames=3, width=40, height=30)


def test_exported_frames_render_as_the_model_does_at_that_time(scene, tmp_path):
    dataset = open_dataset(scene.root)
    model = moving_model(scene.model)  # lite: its colour is exact as degree-0 SH
    written = export_ply_frames(model, tmp_path / "frames", frames="0:3", dataset=dataset)
    assert [p.name for p in written] == ["frame_000000.ply", "frame_000001.ply", "frame_000002.ply"]
    for frame, path in zip(range(3), written):
        ply = PlyData.read(str(path))["vertex"]  # plyfile, as any 3DGS tool reads it
        assert [p.name for p in ply.properties] == INRIA_FIELDS
        static = read_inria_ply(path)
        camera = next(c for c in dataset.test if c.frame == frame)
        expected = model.render(camera, t=camera.time, background=torch.zeros(3), backend="torch").rgb
        inputs = static_render_inputs(static)
        got = rasterize(**inputs, K=torch.tensor(camera.K, dtype=torch.float32),
                        viewmat=torch.tensor(camera.w2c, dtype=torch.float32), width=camera.width,
                        height=camera.height, background=torch.zeros(3), backend="torch",
                        near_plane=camera.near).image
        assert float(psnr(got.detach(), expected.detach())) > 60  # float32 PLY round trip only
        # Gaussians invisible at that time are left out, the others all kept.
        visible = int((model.temporal_opacity(camera.time) >= 1 / 255).sum())
        assert len(static) == visible < model.num_gaussians
    record = json.loads((tmp_path / "frames" / "export.json").read_text())
    assert [f["frame"] for f in record["frames"]] == [0, 1, 2] and "exact" in record["colour"]


def test_full_model_colour_is_its_decoder_per_gaussian_along_the_mean_training_view(scene):
    dataset = open_dataset(scene.root)
    rng = np.random.default_rng(4)
    cloud = SimpleNamespace(xyz=rng.normal(0, 0.5, (50, 3)), rgb=rng.uniform(0, 1, (50, 3)), time=rng.uniform(0, 1, 50))
    model = STGModel.from_points(cloud, variant="full")
    with torch.no_grad():
        model.params["features_t"].normal_(0, 0.3, generator=torch.Generator().manual_seed(5))
        model.params["trbf_scale"].fill_(3.0)
    t = 0.4
    origin = training_view_origin(dataset)
    got = gaussians_at(model, t, origin)
    # Written out here from the decoder's definition (docs/model.md): sigmoid(albedo + W2 relu(W1 [spec, tfeat,
    # origin, direction])), features at t = [features_dc(6), (t - mu_t) features_t].
    p = {k: v.detach().double().numpy() for k, v in model.params.items()}
    w1 = model.decoder.mlp1.weight.detach().double().numpy()[:, :, 0, 0]
    w2 = model.decoder.mlp2.weight.detach().double().numpy()[:, :, 0, 0]
    d = t - p["trbf_center"]
    means = p["xyz"] + p["motion"][:, 0:3] * d + p["motion"][:, 3:6] * d**2 + p["motion"][:, 6:9] * d**3
    direction = (means - origin) / np.linalg.norm(means - origin, axis=1, keepdims=True)
    x = np.concatenate([p["features_dc"][:, 3:6], d * p["features_t"], np.broadcast_to(origin, means.shape), direction], 1)
    rgb = 1 / (1 + np.exp(-(p["features_dc"][:, 0:3] + np.maximum(x @ w1.T, 0) @ w2.T)))
    np.testing.assert_allclose(got.rgb, rgb, atol=1e-5)
    np.testing.assert_allclose(got.means, means, atol=1e-5)


def test_sh_dc_round_trip_and_the_cli(scene, tmp_path, capsys):
    static = gaussians_at(scene.model, 0.5, np.zeros(3))
    assert SH_C0 == pytest.approx(0.5 / np.sqrt(np.pi))
    run = tmp_path / "run"
    (run / "point_cloud" / "iteration_1").mkdir(parents=True)
    scene.model.save(run / "point_cloud" / "iteration_1")
    (run / "config.json").write_text(json.dumps({"data": {"path": str(scene.root)}, "model": {}, "train": {},
                                                 "compaction": None}))
    assert main(["export", str(run), "--out", str(tmp_path / "out"), "--frames", "1:2"]) == 0
    assert "1 static 3DGS PLY" in capsys.readouterr().out
    back = read_inria_ply(tmp_path / "out" / "frame_000001.ply")
    assert len(back) == len(gaussians_at(scene.model, 1 / 3, np.zeros(3)))
    np.testing.assert_allclose(back.rgb[:5], gaussians_at(scene.model, 1 / 3, np.zeros(3)).rgb[:5], atol=1e-5)
    assert static.rgb.shape[1] == 3
    # A selection outside the data is a clear error (exit status 2, the frames named), and nothing is written.
    assert main(["export", str(run), "--out", str(tmp_path / "bad"), "--frames", "7:9"]) == 2
    assert "frames 7:9" in capsys.readouterr().err and not (tmp_path / "bad").exists()
    # Exported again into the same folder: only this export's frames are there (the earlier ones were left beside
    # them, unlisted); a folder with other files in it is refused, not replaced.
    assert main(["export", str(run), "--out", str(tmp_path / "out"), "--frames", "0:1"]) == 0
    listed = [f["file"] for f in json.loads((tmp_path / "out" / "export.json").read_text())["frames"]]
    assert listed == ["frame_000000.ply"] and sorted(p.name for p in (tmp_path / "out").iterdir()) == \
        ["export.json", "frame_000000.ply"]
    (tmp_path / "out" / "notes.txt").write_text("mine")
    assert main(["export", str(run), "--out", str(tmp_path / "out")]) == 2
    assert "notes.txt" in capsys.readouterr().err and (tmp_path / "out" / "notes.txt").is_file()


def _read_splatv(path):
    """An independent reader of splaTV's file, from the format's description (two uint32: magic 0x674B and the JSON
    length; the JSON chunk list; then 16 uint32 per Gaussian: float32 x y z; half pairs (low 16 bits first) of the
    quaternion, the scales, the 9 motion coefficients, the angular velocity and (mu_t, exp(s_t)); RGBA bytes)."""
    import struct

    data = path.read_bytes()
    magic, length = struct.unpack_from("<II", data, 0)
    assert magic == 0x674B
    chunks = json.loads(data[8 : 8 + length].decode("utf-8"))
    splat = chunks[0]
    words = np.frombuffer(data[8 + length : 8 + length + splat["size"]], dtype="<u4")
    assert words.size == splat["texwidth"] * splat["texheight"] * 4

    def halves(column):
        return np.stack([(column & 0xFFFF).astype(np.uint16).view(np.float16),
                         (column >> 16).astype(np.uint16).view(np.float16)], axis=1).astype(np.float64)

    return splat, words, halves


def test_splatv_file_holds_the_model_as_an_independent_reader_sees_it(scene, tmp_path):
    dataset = open_dataset(scene.root)
    model = moving_model(scene.model)
    with torch.no_grad():
        model.params["rotation"].mul_(1.7)  # unnormalised, as STG stores them
    from stgc.eval.export import export_splatv

    path = export_splatv(model, tmp_path / "m.splatv", dataset=dataset)
    splat, words, halves = _read_splatv(path)
    n = model.num_gaussians
    rows = words[: 16 * n].reshape(n, 16)
    assert not words[16 * n :].any()  # the texture's padding
    p = {k: v.detach().double().numpy() for k, v in model.params.items()}
    np.testing.assert_array_equal(rows[:, 0:3].view(np.float32), p["xyz"].astype(np.float32))
    half = dict(rtol=2e-3, atol=1e-4)  # IEEE half precision
    np.testing.assert_allclose(np.concatenate([halves(rows[:, 3]), halves(rows[:, 4])], 1), p["rotation"], **half)
    np.testing.assert_allclose(np.concatenate([halves(rows[:, 5]), halves(rows[:, 6])[:, :1]], 1),
                               np.exp(p["scaling"]), **half)
    motion = np.concatenate([halves(rows[:, 8 + k]) for k in range(5)], 1)[:, :9]
    np.testing.assert_allclose(motion, p["motion"], **half)
    np.testing.assert_allclose(np.concatenate([halves(rows[:, 13]), halves(rows[:, 14])], 1), p["omega"], **half)
    np.testing.assert_allclose(halves(rows[:, 15]), np.concatenate([p["trbf_center"], np.exp(p["trbf_scale"])], 1), **half)
    rgba = rows[:, 7:8].view(np.uint8).reshape(n, 4).astype(np.float64)
    np.testing.assert_allclose(rgba[:, :3], np.clip(p["features_dc"] * 255, 0, 255), atol=0.51)
    np.testing.assert_allclose(rgba[:, 3], 255 / (1 + np.exp(-p["opacity"][:, 0])), atol=0.51)
    names = [c["img_name"] for c in splat["cameras"]]
    assert sorted(names) == sorted({str(c.name) for c in dataset.cameras})
    first = next(c for c in dataset.cameras if str(c.name) == splat["cameras"][0]["img_name"])
    np.testing.assert_allclose(splat["cameras"][0]["position"], first.center, atol=1e-9)


def _splatv_view_matrix(camera):
    """splaTV's getViewMatrix (its viewer's main.js / hybrid.js), written out: a column-major 4 x 4 from the camera's
    `rotation` rows R and `position` t; its columns are R's rows and -(t R[:, j])."""
    R = np.asarray(camera["rotation"], np.float64).ravel()
    t = np.asarray(camera["position"], np.float64)
    flat = [R[0], R[1], R[2], 0.0,
            R[3], R[4], R[5], 0.0,
            R[6], R[7], R[8], 0.0,
            -t[0] * R[0] - t[1] * R[3] - t[2] * R[6],
            -t[0] * R[1] - t[1] * R[4] - t[2] * R[7],
            -t[0] * R[2] - t[1] * R[5] - t[2] * R[8],
            1.0]
    return np.asarray(flat).reshape(4, 4).T  # column-major: each group of four is a column


def test_splatv_cameras_give_splatvs_viewer_the_datasets_view_matrices(scene, tmp_path):
    """splaTV builds each camera's view matrix from the JSON's `rotation` and `position` (getViewMatrix). The test
    checked only the names and the first centre, so a transposed rotation (world-to-camera rows, the other common
    convention) or swapped focal lengths would have passed; here the viewer's matrix must be the camera's w2c."""
    from stgc.eval.export import export_splatv

    dataset = open_dataset(scene.root)
    splat, _, _ = _read_splatv(export_splatv(scene.model, tmp_path / "m.splatv", dataset=dataset))
    by_name = {str(c.name): c for c in [*dataset.test, *dataset.train]}
    assert len(splat["cameras"]) == len(by_name)
    for entry in splat["cameras"]:
        cam = by_name[entry["img_name"]]
        np.testing.assert_allclose(_splatv_view_matrix(entry), cam.w2c, atol=1e-9)
        assert (entry["fx"], entry["fy"]) == (float(cam.K[0, 0]), float(cam.K[1, 1]))
        assert (entry["width"], entry["height"]) == (cam.width, cam.height)
    # The rotation is not symmetric in these cameras: the transposed convention would fail above.
    assert not np.allclose(np.asarray(splat["cameras"][0]["rotation"]), np.asarray(splat["cameras"][0]["rotation"]).T)
    # These cameras have square pixels (fx = fy); one whose focal lengths differ shows a swap.
    import dataclasses

    from stgc.eval.export import splatv_cameras

    K = dataset.test[0].K.copy()
    K[1, 1] *= 1.25
    entry = splatv_cameras(SimpleNamespace(test=[dataclasses.replace(dataset.test[0], K=K)], train=[]))[0]
    assert (entry["fx"], entry["fy"]) == (K[0, 0], K[1, 1]) and K[0, 0] != K[1, 1]


def _write_run(root, model, data_root, **data):
    (root / "point_cloud" / "iteration_1").mkdir(parents=True)
    model.save(root / "point_cloud" / "iteration_1")
    (root / "config.json").write_text(json.dumps({"data": {"path": str(data_root), **data}, "model": {}, "train": {},
                                                 "compaction": None}))
    return root


def test_exports_record_the_models_near_plane_and_warn_where_viewers_cull_nearer(scene, tmp_path, capsys):
    """The model culls Gaussians closer than its near plane to a camera (1.0 on Panoptic data); gsplat and nerfstudio
    cull at 0.01, the INRIA viewers at 0.2, so Gaussians the model never showed a camera fog the exported views from
    near it (27.86 against 6.90 dB on a Panoptic camera). The exports did not say which near plane the model used, and
    nothing warned."""
    run = _write_run(tmp_path / "run", scene.model, scene.root, near_plane=None)  # the format's: Panoptic's 1.0
    assert main(["export", str(run), "--out", str(tmp_path / "frames"), "--frames", "0:1"]) == 0
    err = capsys.readouterr().err
    assert "near plane" in err and "0.01" in err and "near_plane" in err and "export.json" in err
    assert json.loads((tmp_path / "frames" / "export.json").read_text())["near_plane"] == 1.0
    assert main(["export", str(run), "--format", "splatv", "--out", str(tmp_path / "m.splatv")]) == 0
    assert "near plane" in capsys.readouterr().err
    splat, _, _ = _read_splatv(tmp_path / "m.splatv")
    assert splat["near_plane"] == 1.0
    # A model with STG's own 0.2: the viewers show what it shows (INRIA's) or cull nearer by little; recorded, no
    # warning.
    official = _write_run(tmp_path / "official", scene.model, scene.root, near_plane=0.2)
    assert main(["export", str(official), "--out", str(tmp_path / "frames02"), "--frames", "0:1"]) == 0
    assert "near plane" not in capsys.readouterr().err
    assert json.loads((tmp_path / "frames02" / "export.json").read_text())["near_plane"] == 0.2


def test_a_frame_listed_twice_is_exported_once(scene, tmp_path, capsys):
    """`--frames 2,0,2` said it wrote 3 files (2 exist: the second frame 2 replaced the first) and export.json listed
    frame 2 twice; each frame is exported once, in the order first given."""
    from stgc.eval.video import frame_selection

    assert frame_selection("0,2,0", [0, 1, 2]) == [0, 2, 0]  # a clip may play a frame again
    run = _write_run(tmp_path / "run", scene.model, scene.root)
    assert main(["export", str(run), "--out", str(tmp_path / "out"), "--frames", "2,0,2"]) == 0
    assert "wrote 2 static 3DGS PLY" in capsys.readouterr().out
    record = json.loads((tmp_path / "out" / "export.json").read_text())
    assert [f["frame"] for f in record["frames"]] == [2, 0]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["export.json", "frame_000000.ply",
                                                                    "frame_000002.ply"]


def test_a_full_models_splatv_colour_is_its_decoded_colour_at_its_own_time():
    """splaTV has one colour per Gaussian: the full model's decoder output at the Gaussian's mu_t (its time feature
    zero there), along the ray from the origin given; the same as the decoded colour of the frame export at that
    time (another path through the model: features_at, means_at)."""
    from stgc.codec.synthetic import synthetic_model
    from stgc.eval.export import splatv_colours
    from stgc.model import MIN_VISIBLE_OPACITY

    arrays, decoder = synthetic_model(40, "full", seed=2)
    model = STGModel.from_ply_arrays(arrays, "full", decoder, scene_extent=3.0)
    origin = np.array([0.3, -0.2, 4.0])
    colours = splatv_colours(model, origin)
    mu_t = model.params["trbf_center"].detach().numpy().ravel()
    checked = 0
    for i in range(model.num_gaussians):
        visible = np.flatnonzero((model.temporal_opacity(float(mu_t[i])) >= MIN_VISIBLE_OPACITY).numpy())
        if i not in visible:
            continue
        at_own_time = gaussians_at(model, float(mu_t[i]), origin)
        np.testing.assert_allclose(colours[i], at_own_time.rgb[np.searchsorted(visible, i)], atol=1e-5)
        checked += 1
    assert checked > 20
    assert np.ptp(colours, axis=0).max() > 0.05  # the colours differ between Gaussians: a comparison that can fail


def test_a_splatv_temporal_scale_beyond_half_range_is_written_as_the_largest_half(scene, tmp_path):
    """exp(s_t) above 65504 (the largest half float; 421 Gaussians of a trained Panoptic model) was cast to inf, with a
    numpy overflow warning that `stgc export` printed. Written as 65504 instead: the viewer's temporal factor
    exp(-(dt / 65504)^2) is 1 there to 2.4e-10, as it is for the model's scale."""
    import warnings

    from stgc.eval.export import export_splatv

    dataset = open_dataset(scene.root)
    model = moving_model(scene.model)
    with torch.no_grad():
        model.params["trbf_scale"][:5, 0] = torch.tensor([11.0, 12.0, 30.0, 100.0, 11.09])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no overflow warning
        path = export_splatv(model, tmp_path / "m.splatv", dataset=dataset)
    _, words, halves = _read_splatv(path)
    stored = halves(words[: 16 * model.num_gaussians].reshape(-1, 16)[:, 15])[:, 1]
    assert np.isfinite(stored).all()
    np.testing.assert_array_equal(stored[1:4], 65504.0)
    np.testing.assert_allclose(stored[[0, 4]], np.exp([11.0, 11.09]), rtol=5e-4)
    np.testing.assert_allclose(stored[5:], np.exp(model.params["trbf_scale"].detach().numpy()[5:, 0]), rtol=5e-4)


def test_an_export_onto_a_symbolic_link_replaces_the_earlier_export_it_points_to(scene, tmp_path, capsys):
    """`--out LINK`, LINK a symbolic link to an earlier export: the swap into place renamed the link aside and put a
    new folder (or file, for splatv) in its place, so the link was gone, its target kept the earlier export's
    frames, and a `.LINK.*.old` link was left beside it. The export goes into the link's target instead."""
    import os

    run = _write_run(tmp_path / "run", scene.model, scene.root)
    exports = tmp_path / "exports"
    assert main(["export", str(run), "--out", str(exports / "real")]) == 0
    os.symlink("real", exports / "lnk")
    assert main(["export", str(run), "--out", str(exports / "lnk"), "--frames", "0:1"]) == 0
    assert (exports / "lnk").is_symlink() and os.readlink(exports / "lnk") == "real"
    assert sorted(p.name for p in (exports / "real").iterdir()) == ["export.json", "frame_000000.ply"]
    assert sorted(p.name for p in exports.iterdir()) == ["lnk", "real"]  # nothing left beside them

    assert main(["export", str(run), "--format", "splatv", "--out", str(exports / "real.splatv")]) == 0
    first = (exports / "real.splatv").read_bytes()
    os.symlink("real.splatv", exports / "lnk.splatv")
    other = _write_run(tmp_path / "other", moving_model(scene.model), scene.root)
    assert main(["export", str(other), "--format", "splatv", "--out", str(exports / "lnk.splatv")]) == 0
    assert (exports / "lnk.splatv").is_symlink() and (exports / "real.splatv").read_bytes() != first
    _read_splatv(exports / "lnk.splatv")  # a whole splaTV file, read through the link
    assert sorted(p.name for p in exports.iterdir()) == ["lnk", "lnk.splatv", "real", "real.splatv"]

    # A link that cannot be followed (a loop) is named, not a traceback; nothing is written.
    os.symlink("loop", exports / "loop")
    capsys.readouterr()
    assert main(["export", str(run), "--out", str(exports / "loop")]) == 2
    assert "loop: is a symbolic link that cannot be followed" in capsys.readouterr().err
    assert sorted(p.name for p in exports.iterdir()) == ["lnk", "lnk.splatv", "loop", "real", "real.splatv"]


def test_an_empty_frame_range_is_called_empty_not_outside_the_data(scene, tmp_path, capsys):
    """`--frames 1:1` (or 2:1) was reported as "not within the dataset's frames", though frame 1 is one of them:
    the range is empty, A:B taking frames A to B-1."""
    from stgc.errors import DataError
    from stgc.eval.video import frame_selection

    for empty in ("1:1", "2:1"):
        with pytest.raises(DataError, match=rf"frames {empty} is empty: A:B takes frames A to B-1") as info:
            frame_selection(empty, [0, 1, 2])
        assert "not within" not in str(info.value)
    assert frame_selection("1:2", [0, 1, 2]) == [1]
    with pytest.raises(DataError, match="not within the dataset's frames 0:3"):
        frame_selection("2:4", [0, 1, 2])  # outside the data: still said so
    run = _write_run(tmp_path / "run", scene.model, scene.root)
    assert main(["export", str(run), "--out", str(tmp_path / "out"), "--frames", "1:1"]) == 2
    err = capsys.readouterr().err
    assert "frames 1:1 is empty" in err and "1:2" in err and not (tmp_path / "out").exists()


def test_a_zero_quaternion_is_exported_as_no_rotation_not_nan(scene, tmp_path):
    """A Gaussian whose rotation and angular velocity are zero (an official error-guided insertion never trained) is
    drawn unrotated by stgc and gsplat; exported as normalised zeros, readers that divide by the norm got NaN."""
    from stgc.eval.export import export_splatv

    dataset = open_dataset(scene.root)
    model = moving_model(scene.model)
    with torch.no_grad():
        model.params["rotation"][:2] = 0.0
        model.params["omega"][0] = 0.0  # row 1 keeps its angular velocity: q + omega dt turns it away from t = mu_t
        model.params["trbf_center"][:2] = 0.5
    static = gaussians_at(model, 0.5, training_view_origin(dataset))
    assert static.quats[:2].tolist() == [[1.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]]
    [path] = export_ply_frames(model, tmp_path / "frames", frames=[1], dataset=dataset)  # frame 1 of 3: t = 1/3
    quats = read_inria_ply(path).quats
    assert np.isfinite(quats).all() and [1.0, 0.0, 0.0, 0.0] in quats.tolist()  # row 0 is there, unrotated
    _, words, halves = _read_splatv(export_splatv(model, tmp_path / "m.splatv", dataset=dataset))
    rows = words[: 16 * model.num_gaussians].reshape(-1, 16)
    quats = np.concatenate([halves(rows[:, 3]), halves(rows[:, 4])], axis=1)
    assert quats[0].tolist() == [1.0, 0.0, 0.0, 0.0]  # the viewer normalises q + omega dt: never 0 now
    assert quats[1].tolist() == [0.0, 0.0, 0.0, 0.0]  # as stored: q + omega dt is not 0 away from mu_t
    np.testing.assert_allclose(quats[2:], model.params["rotation"].detach().numpy()[2:], rtol=1e-3, atol=1e-3)
