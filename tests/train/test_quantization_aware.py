"""Rate-aware fine-tuning (train.quantization_aware): training that sees the codec's quantization loses less PSNR
when the model is really encoded and decoded than the same training without it."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from scenes import write_panoptic_scene

from stgc import machine
from stgc.codec import CodecConfig, compress_run, load_model, read_stgc_header
from stgc.data import open_dataset
from stgc.model import MIN_VISIBLE_OPACITY, STGModel
from stgc.train import TrainConfig, train
from stgc.train.config import DensifyConfig, QuantizationAwareConfig
from stgc.train.loop import Trainer, learning_rates, xyz_learning_rate
from stgc.train.quantization import RateTerm

QUALITY = 1  # the coarsest level: its loss is large enough to see on a tiny scene


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return write_panoptic_scene(tmp_path_factory.mktemp("qat"), views=8, frames=2, width=64, height=48)


def _config(window: int, iterations: int = 300, simulate: bool = True, allocation: str = "ladder",
            **over) -> TrainConfig:
    options = dict(iterations=iterations, densify=DensifyConfig(enabled=False, opacity_reset_interval=0),
                   colour_correction="off", save_iterations=(), checkpoint_every=0, log_every=10, progress=False,
                   tensorboard=False, seed=1, eval_at_end=False,
                   quantization_aware=QuantizationAwareConfig(iterations=window, quality=QUALITY, simulate=simulate,
                                                              allocation=allocation))
    return TrainConfig(**{**options, **over})


def _psnr(model: STGModel, dataset) -> float:
    scores = []
    for cam in dataset.train:
        with torch.no_grad():
            rgb = model.render(cam, t=cam.time, background=torch.zeros(3)).rgb.clamp(0, 1).numpy().astype(np.float64)
        truth = np.asarray(dataset.load_image(cam))[..., :3].astype(np.float64) / 255.0
        scores.append(-10 * np.log10(np.mean((rgb - truth) ** 2)))
    return float(np.mean(scores))


@pytest.fixture
def threads_restored():
    """The test below trains at 1 thread (`train.threads`); the rest of the session keeps its own counts."""
    with machine.threads(0):
        yield


def test_training_through_the_codec_loses_less_when_really_encoded(scene, tmp_path, threads_restored):
    """Three runs from the same start, identical for 200 iterations; the last 100: as before (plain), at the
    window's lower learning rates (control), or also through the codec's quantization (aware). Each model is then
    really encoded and decoded at the coarsest quality and scored on the training views; three seeds, averaged."""
    dataset = open_dataset(scene.root)
    decoded: dict[str, list[float]] = {"plain": [], "control": [], "aware": []}
    floats: dict[str, list[float]] = {"plain": [], "control": [], "aware": []}
    for seed in (1, 2, 3):
        # One thread: the same rounding (the order of the rasterizer's sums) on every machine with 2 or more CPUs.
        for name, config in (("plain", _config(0, seed=seed, threads=1)),
                             ("control", _config(100, simulate=False, seed=seed, threads=1)),
                             ("aware", _config(100, seed=seed, threads=1))):  # fmt: skip
            run = tmp_path / f"{name}{seed}"
            start = STGModel.from_ply_arrays(scene.model.to_ply_arrays(), "lite", None, scene_extent=3.3)
            train(dataset, None, None, config, None, run, model=start)
            floats[name].append(_psnr(STGModel.load(run), dataset))
            compress_run(run, tmp_path / f"{name}{seed}.stgc", config=CodecConfig(quality=QUALITY, allocation="ladder"))
            decoded[name].append(_psnr(load_model(tmp_path / f"{name}{seed}.stgc"), dataset))
    print({k: [(round(f, 2), round(d, 2)) for f, d in zip(floats[k], decoded[k])] for k in floats})
    # One seed's run is chaotic at this size (the same code and seed at 1 and 2 threads, which differ only in the
    # order of the rasterizer's sums, gave the aware run a quantization loss of 6.4 and 2.8 dB), hence the mean over
    # three seeds at one thread. What the method claims: a smaller quantization loss than the control's, which
    # differs only by the quantization in the forward, and than plain training's, by margins well outside the seeds'
    # spread; and a better decoded model than the control's, whose size (+0.4 to +1.1 dB on the mean so far) moves
    # with every change of rounding, so no margin. The measured means: benchmarks/RESULTS.md, sessions 46 and 47.
    loss = {k: float(np.mean(floats[k]) - np.mean(decoded[k])) for k in floats}
    assert loss["aware"] < loss["control"] - 2.0
    assert loss["aware"] < loss["plain"] - 1.0
    assert np.mean(decoded["aware"]) > np.mean(decoded["control"])


def test_the_window_is_the_run_s_last_iterations(scene, tmp_path):
    dataset = open_dataset(scene.root)
    start = STGModel.from_ply_arrays(scene.model.to_ply_arrays(), "lite", None, scene_extent=3.3)
    seen, rates = [], {}
    config = _config(30, iterations=80)
    trainer = Trainer(dataset, None, None, config, None, tmp_path / "run", model=start,
                      callback=lambda i, row: (seen.append((i, bool(row.get("quantized")))),
                                               rates.__setitem__(i, row["lr_xyz"])))
    trainer.run()
    assert [i for i, quantized in seen if quantized] == list(range(51, 81))
    # Inside the window every learning rate is scaled down: xyz on its decay, the others from their constants.
    for i in (50, 51, 80):
        expected = xyz_learning_rate(config, trainer.extent, i, 80) * (0.01 if i > 50 else 1.0)
        assert rates[i] == pytest.approx(expected)
    assert all(g["lr"] == pytest.approx(0.01 * learning_rates(trainer.cfg, trainer.extent)[g["name"]])
               for g in trainer.optimizer.param_groups if g["name"] != "xyz")
    with pytest.raises(ValueError, match="quantization_aware.iterations"):
        from stgc.config import validate_config

        validate_config(TrainConfig(iterations=10, quantization_aware=QuantizationAwareConfig(iterations=11)), "train")



def test_the_optimised_allocation_is_measured_once_when_the_window_opens_and_kept_across_a_resume(scene, tmp_path,
                                                                                                 monkeypatch):
    """allocation 'optimised' (the default, as stgc compress): the rd-optimised depths are measured on the training
    views at the window's first iteration, simulated for the rest of it, recorded in the summary, and a run killed
    inside the window resumes with the same depths instead of measuring again on a different model."""
    import stgc.train.quantization as quantization

    measured = []
    real = quantization.optimise_on_views
    monkeypatch.setattr(quantization, "optimise_on_views",
                        lambda *a, **k: measured.append(1) or real(*a, **k))
    dataset = open_dataset(scene.root)
    start = STGModel.from_ply_arrays(scene.model.to_ply_arrays(), "lite", None, scene_extent=3.3)
    run = tmp_path / "run"
    config = _config(20, iterations=40, allocation="optimised", checkpoint_every=5)
    train(dataset, None, None, dataclasses.replace(config, stop_after=25), None, run, model=start)
    assert len(measured) == 1  # at iteration 21
    settings = torch.load(run / "checkpoint.pt", weights_only=False)["quantization_aware"]["settings"]
    assert settings is not None and set(settings[0]) >= {"POSI", "FDC_", "SCAL"}
    summary = train(dataset, None, None, config, None, run, resume=True)
    assert len(measured) == 1  # not measured again after the resume
    assert summary["quantization_aware_allocation"]["depths"] and summary["finished"]
    seen = torch.load(run / "checkpoint.pt", weights_only=False)["quantization_aware"]["settings"]
    assert [dict(x) for x in seen] == [dict(x) for x in settings]


def test_compress_stores_the_depths_the_window_trained_through(scene, tmp_path, monkeypatch):
    """A model trained through an optimised window is written at the window's depths (not measured again, which
    would spend the quality's budget a second time): the decoded file is exactly what the window's simulation
    rendered with the depths kept in the checkpoint. Another quality, an earlier iteration or
    codec.allocation=optimised measure them again; 'trained' refuses a model without such depths."""
    import stgc.codec.files as files
    from stgc.codec import read_stgc, read_stgc_metadata
    from stgc.codec.files import WINDOW_MODE, written_without_window_depths
    from stgc.codec.format import simulate_quantization
    from stgc.errors import DataError

    dataset = open_dataset(scene.root)
    start = STGModel.from_ply_arrays(scene.model.to_ply_arrays(), "lite", None, scene_extent=3.3)
    run = tmp_path / "run"
    train(dataset, None, None, _config(20, iterations=40, allocation="optimised", save_iterations=(10, 40)), None,
          run, model=start)
    group_bits, step_scales = torch.load(run / "checkpoint.pt", weights_only=False)["quantization_aware"]["settings"]

    written = compress_run(run, run / "model_q1.stgc", quality=QUALITY)
    assert read_stgc_metadata(written.path)["allocation"]["mode"] == WINDOW_MODE
    assert not written_without_window_depths(written.path, CodecConfig(quality=QUALITY))
    monkeypatch.chdir(tmp_path)  # a run named as the user types it, relative: the same depths
    assert files.window_depths(Path("run")) is not None
    assert files.window_depths(Path("run") / "point_cloud" / "iteration_40") is not None
    final = STGModel.load(run)
    visible = (final.peak_temporal_opacity() >= MIN_VISIBLE_OPACITY * (1 - 1e-3)).numpy()  # as compress drops
    arrays = {k: v[visible] for k, v in final.to_ply_arrays().items()}
    simulated = simulate_quantization(arrays, "lite", QUALITY, group_bits=group_bits, step_scales=step_scales)
    decoded = read_stgc(written.path).arrays

    def rows(columns: dict) -> np.ndarray:  # the file stores the Gaussians in Morton order
        table = np.stack([np.asarray(columns[k], np.float64) for k in sorted(simulated)], axis=1)
        return table[np.lexsort(table.T[::-1])]

    np.testing.assert_array_equal(rows(decoded), rows(simulated))

    few = CodecConfig(quality=QUALITY, allocation_views=2)  # measured again: two views are enough to see which
    others = {"q2": compress_run(run, tmp_path / "q2.stgc", config=dataclasses.replace(few, quality=2)),
              "optimised": compress_run(run, tmp_path / "o.stgc",
                                        config=dataclasses.replace(few, allocation="optimised")),
              "iteration 10": compress_run(run / "point_cloud" / "iteration_10", tmp_path / "i.stgc", config=few)}
    for name, result in others.items():
        assert read_stgc_metadata(result.path)["allocation"]["mode"] == "rd-optimised", name
    # The runner writes RUN/model_q<Q>.stgc again when an earlier stgc measured its depths by default, never when
    # they were asked for.
    (run / "model_q1.stgc").write_bytes((tmp_path / "o.stgc").read_bytes())
    assert not written_without_window_depths(run / "model_q1.stgc", CodecConfig(quality=QUALITY))
    with monkeypatch.context() as patch:
        patch.setattr(files, "window_depths", lambda source: None)  # as the default wrote it before session 27
        compress_run(run, run / "model_q1.stgc", config=few)
    assert written_without_window_depths(run / "model_q1.stgc", CodecConfig(quality=QUALITY))
    for source, quality in ((run, 2), (run / "point_cloud" / "iteration_10", QUALITY)):
        with pytest.raises(DataError, match="allocation=trained"):
            compress_run(source, tmp_path / "t.stgc", config=CodecConfig(quality=quality, allocation="trained"))
    shutil.rmtree(run / "point_cloud" / "iteration_40")  # a partial copy: the latest model is from before the window
    assert files.window_depths(run) is None


def test_the_rate_term_trades_distortion_for_a_smaller_file(scene, tmp_path):
    """Two runs, identical but for lambda (train.quantization_aware.rate_weight) in the window: the one that pays
    for its estimated bits writes a smaller real file at the same depths, and its estimate falls while it trains."""
    dataset = open_dataset(scene.root)
    sizes, rates = {}, {}
    for name, weight in (("no_rate", 0.0), ("rate", 0.05)):
        run = tmp_path / name
        start = STGModel.from_ply_arrays(scene.model.to_ply_arrays(), "lite", None, scene_extent=3.3)
        seen: list[float] = []
        config = _config(100, iterations=200)
        config = dataclasses.replace(config, quantization_aware=dataclasses.replace(
            config.quantization_aware, rate_weight=weight))
        Trainer(dataset, None, None, config, None, run, model=start,
                callback=lambda i, row: seen.append(row["rate_bits"]) if "rate_bits" in row else None).run()
        rates[name] = seen
        compress_run(run, tmp_path / f"{name}.stgc", config=CodecConfig(quality=QUALITY, allocation="ladder"))
        sections = read_stgc_header(tmp_path / f"{name}.stgc").section_bytes()
        sizes[name] = sum(sections[tag] for tag in RateTerm.GROUPS if tag in sections)
    print(sizes, rates["rate"][:3], rates["rate"][-3:])
    # Measured: the estimate 70.6 -> 54.7 bits per Gaussian over the window (before the quaternion index was priced:
    # about 2 bits more each since); those sections 4,777 -> 3,918 bytes
    # (the whole file 9,585 -> 8,786).
    assert rates["no_rate"] == [] and len(rates["rate"]) == 100
    assert np.mean(rates["rate"][-10:]) < 0.85 * np.mean(rates["rate"][:10])
    assert sizes["rate"] < 0.95 * sizes["no_rate"]


def test_a_rate_term_needs_the_simulation():
    from stgc.config import validate_config

    with pytest.raises(ValueError, match="rate_weight"):
        validate_config(TrainConfig(iterations=10, quantization_aware=QuantizationAwareConfig(
            iterations=5, simulate=False, rate_weight=0.1)), "train")
    with pytest.raises(ValueError, match="rate_weight"):
        validate_config(TrainConfig(iterations=10, quantization_aware=QuantizationAwareConfig(
            iterations=5, rate_weight=-1.0)), "train")


def test_the_rate_term_sees_each_component_in_the_codec_s_own_domain():
    """What the rate term differentiates must be what the codec quantizes: the values it computes from the
    parameters (sigmoid opacity, smallest three of the canonical quaternion, motion times its time span), put
    through the codec's own quantizers, give the codec's codes (float32 against float64 may flip a rounding tie)."""
    from stgc.codec.format import quantized_groups
    from stgc.codec.quantize import quantize
    from stgc.codec.synthetic import synthetic_model
    from stgc.train.quantization import _stored_components, _visible

    arrays, decoder = synthetic_model(3000, seed=5)
    model = STGModel.from_ply_arrays(arrays, "full", decoder, scene_extent=3.0)
    keep = _visible(model)
    groups = quantized_groups({k: v[keep] for k, v in model.to_ply_arrays().items()}, "full", QUALITY)
    rows = torch.from_numpy(np.flatnonzero(keep))
    checked = set()
    for group in groups:
        if group.tag not in RateTerm.GROUPS:
            continue
        for row, (values, quantizer) in enumerate(zip(_stored_components(model, group, rows), group.quantizers)):
            codes = quantize(values.detach().double().numpy(), quantizer).astype(np.int64)
            expected = group.codes[row].astype(np.int64)
            assert np.abs(codes - expected).max() <= 1, (group.tag, row)
            assert np.mean(codes == expected) > 0.99, (group.tag, row)
        checked.add(group.tag)
    assert checked == set(RateTerm.GROUPS)


def test_on_the_codec_s_own_values_the_rate_term_is_the_entropy_of_every_stored_row():
    """A decoded model's values lie on the codes, so the interpolated lengths are the codes' own: their sum is the
    order-0 entropy of every row the GROUPS store, the quaternion's largest-component index included (about 2 bits
    a Gaussian that the mask's price once left out, although its help says every section is priced)."""
    from stgc.codec.format import decode, encode, quantized_groups
    from stgc.codec.rate import entropy_bits
    from stgc.codec.synthetic import synthetic_model
    from stgc.train.quantization import _visible

    arrays, decoder = synthetic_model(3000, seed=5)
    first = STGModel.from_ply_arrays(arrays, "full", decoder, scene_extent=3.0)
    visible = {k: v[_visible(first)] for k, v in first.to_ply_arrays().items()}
    model = STGModel.from_ply_arrays(decode(encode(visible, "full", first.decoder_state(), QUALITY)).arrays, "full",
                                     decoder, scene_extent=3.0)
    keep = _visible(model)
    groups = quantized_groups({k: v[keep] for k, v in model.to_ply_arrays().items()}, "full", QUALITY)
    priced = float(RateTerm.row_bits(model, keep, groups).detach().sum())
    entropy = sum(entropy_bits(row) for group in groups if group.tag in RateTerm.GROUPS for row in group.codes)
    index = entropy_bits(next(group for group in groups if group.tag == "ROTN").codes[3])
    assert index > 0.01 * entropy  # what leaving it out would miss
    assert abs(priced / entropy - 1) < 0.01  # measured +0.5 % (the pseudo-counts of the code histograms)


def _with_hidden_gaussians(model: STGModel, count: int, seed: int = 0) -> tuple[STGModel, int]:
    """`model` plus `count` opaque Gaussians high above the camera ring, outside every camera's view: they cost
    bits and add nothing to any image. Returns (model, number of real Gaussians, which come first)."""
    arrays = model.to_ply_arrays()
    rng = np.random.default_rng(seed)
    extra = {k: np.repeat(v[:1], count, axis=0) for k, v in arrays.items()}
    extra["x"], extra["y"] = rng.uniform(-1, 1, count).astype(np.float32), rng.uniform(-1, 1, count).astype(np.float32)
    extra["z"] = np.full(count, 20.0, np.float32)
    merged = {k: np.concatenate([v, extra[k]]) for k, v in arrays.items()}
    return STGModel.from_ply_arrays(merged, "lite", None, scene_extent=3.3), len(arrays["x"])


def test_the_learned_mask_drops_the_gaussians_that_cost_bits_and_show_nothing(scene, tmp_path):
    """The scene's model plus 200 Gaussians no camera sees: with the mask, the window removes every hidden one
    (they earn nothing against their price) and keeps enough of the scene to render it nearly as well; the saved
    model is the kept rows. Without the mask the same rate term keeps every row."""
    dataset = open_dataset(scene.root)
    counts, psnrs = {}, {}
    for name, mask in (("rate", False), ("mask", True)):
        start, real = _with_hidden_gaussians(scene.model, 200)
        run = tmp_path / name
        config = _config(200, iterations=200)
        config = dataclasses.replace(config, quantization_aware=dataclasses.replace(
            config.quantization_aware, rate_weight=1e-4, mask=mask, mask_lr=0.05))
        summary = train(dataset, None, None, config, None, run, model=start)
        saved = STGModel.load(run)
        counts[name] = (summary["num_gaussians"], saved.num_gaussians,
                        int((saved.params["xyz"][:, 2] > 10).sum()))
        psnrs[name] = _psnr(saved, dataset)
    print(counts, psnrs)
    assert counts["rate"] == (real + 200, real + 200, 200)
    kept, saved_count, hidden_left = counts["mask"]
    assert kept == saved_count and hidden_left == 0
    # Measured: 525 of the 750 real Gaussians kept, 47.4 dB against 50.9 without the mask (at lambda 1e-5: 633 and
    # 49.0 dB; at 1e-3: 340 and 33.1 dB: lambda sets the trade). A binary mask in the forward pass (tried first)
    # kept 283 at 20.5 dB: every redundant Gaussian dropped at once.
    assert real // 2 < kept < real
    assert psnrs["mask"] > psnrs["rate"] - 5.0


def test_remeasure_at_settle_trains_the_last_fifth_at_depths_measured_on_the_masked_model(scene, tmp_path,
                                                                                         monkeypatch):
    """remeasure_at_settle: the depths are measured when the window opens and again, once, on the model the
    settled mask leaves; the last fifth trains at the second, which the summary records and compress stores."""
    import stgc.train.quantization as quantization
    from stgc.codec import read_stgc_metadata

    measured = []
    real_measure = quantization.optimise_on_views

    def measure(model, *args, **kwargs):
        allocation = real_measure(model, *args, **kwargs)
        measured.append((model.num_gaussians, allocation.summary()))
        return allocation

    monkeypatch.setattr(quantization, "optimise_on_views", measure)
    dataset = open_dataset(scene.root)
    start, real = _with_hidden_gaussians(scene.model, 200)
    config = _config(200, iterations=200, allocation="optimised")
    config = dataclasses.replace(config, quantization_aware=dataclasses.replace(
        config.quantization_aware, rate_weight=1e-4, mask=True, mask_lr=0.05))  # remeasure_at_settle: the default
    summary = train(dataset, None, None, config, None, tmp_path / "run", model=start)
    assert [count for count, _ in measured] == [real + 200, summary["num_gaussians"]]
    assert summary["num_gaussians"] < real  # the hidden ones and some of the scene went before the second
    assert summary["quantization_aware_allocation"] == measured[1][1]
    written = compress_run(tmp_path / "run", tmp_path / "run.stgc", quality=QUALITY)
    assert read_stgc_metadata(written.path)["allocation"]["depths"] == measured[1][1]["depths"]


def test_the_masked_rate_is_the_plain_rate_plus_the_shared_sections_and_its_gradient_is_each_gaussian_s_price():
    """With every Gaussian kept, the masked rate equals the plain bits per Gaussian plus the position and omega
    sections' estimated bits per Gaussian; its gradient with respect to a Gaussian's mask logit is that Gaussian's
    own bits (code lengths plus the shared share) times the sigmoid's slope, over the reference count."""
    from stgc.codec.format import quantized_groups
    from stgc.codec.rate import estimate_section_bits
    from stgc.codec.synthetic import synthetic_model
    from stgc.train.quantization import MASK_INIT_LOGIT, GaussianMask, _visible

    arrays, decoder = synthetic_model(2000, seed=3)
    model = STGModel.from_ply_arrays(arrays, "full", decoder, scene_extent=3.0)
    keep = _visible(model)
    groups = quantized_groups({k: v[keep] for k, v in model.to_ply_arrays().items()}, "full", QUALITY)
    visible = int(keep.sum())
    shared = sum(v for tag, v in estimate_section_bits(groups).items() if tag in ("POSI", "OMGA")) / visible
    plain = RateTerm.bits_per_gaussian(model, keep, groups)
    kept = GaussianMask(model.num_gaussians, 0.01, logits=torch.full((model.num_gaussians,), 40.0),
                        reference_count=visible)
    all_kept = float(RateTerm.masked_bits(model, keep, groups, kept).detach())
    assert all_kept == pytest.approx(float(plain.detach()) + shared, rel=1e-9)
    mask = GaussianMask(model.num_gaussians, 0.01, reference_count=visible)
    masked = RateTerm.masked_bits(model, keep, groups, mask)
    factor = torch.sigmoid(torch.tensor(MASK_INIT_LOGIT, dtype=torch.float64))
    assert float(masked.detach()) == pytest.approx(float(factor) * (float(plain.detach()) + shared), rel=1e-6)
    masked.backward()
    slope = factor * (1 - factor)
    rows = np.flatnonzero(keep)
    own = RateTerm.row_bits(model, keep, groups).detach() + shared
    assert torch.allclose(mask.logits.grad[rows].double(), (slope * own / visible).double(), rtol=1e-5)
    assert float(mask.logits.grad[~torch.from_numpy(keep)].abs().sum()) == 0.0  # never-visible rows cost nothing


def test_a_mask_that_faded_out_every_gaussian_is_an_error_naming_its_price():
    """Settling it emptied the model, which then crashed at the next densification step with a traceback."""
    from stgc.codec.synthetic import synthetic_model
    from stgc.errors import StgcError
    from stgc.train.quantization import GaussianMask, QuantizationSimulation

    arrays, decoder = synthetic_model(50, seed=1)
    model = STGModel.from_ply_arrays(arrays, "full", decoder, scene_extent=3.0)
    simulation = QuantizationSimulation(QuantizationAwareConfig(iterations=5, mask=True, rate_weight=1.0))
    simulation.mask = GaussianMask(model.num_gaussians, 0.01, logits=torch.full((model.num_gaussians,), -5.0))
    with pytest.raises(StgcError, match="faded out all 50 Gaussians.*rate_weight 1.0"):
        simulation.settle_mask(model)
    simulation.mask.logits.data[3] = 5.0  # one kept: settled as usual
    assert int(simulation.settle_mask(model).sum()) == 1


def test_a_mask_needs_a_price():
    from stgc.config import validate_config

    with pytest.raises(ValueError, match="mask"):
        validate_config(TrainConfig(iterations=10, quantization_aware=QuantizationAwareConfig(
            iterations=5, mask=True)), "train")


def test_a_run_killed_while_the_mask_learns_resumes_to_the_same_model(scene, tmp_path):
    """The mask's logits, its Adam state and whether it has settled are in the checkpoint: a run stopped inside the
    window's learning part and resumed ends with the same Gaussians and parameters as one that was not stopped."""
    dataset = open_dataset(scene.root)
    config = _config(40, iterations=60, checkpoint_every=5)
    config = dataclasses.replace(config, quantization_aware=dataclasses.replace(
        config.quantization_aware, rate_weight=1e-3, mask=True, mask_lr=0.2))
    models = {}
    for name, stops in (("whole", []), ("resumed", [30])):
        run = tmp_path / name
        start, _ = _with_hidden_gaussians(scene.model, 50)
        for stop in stops:
            train(dataset, None, None, dataclasses.replace(config, stop_after=stop), None, run, model=start)
        train(dataset, None, None, config, None, run, model=start, resume=bool(stops))
        models[name] = STGModel.load(run)
    assert models["whole"].num_gaussians < scene.model.num_gaussians + 50  # the mask removed some
    # It settled at iteration 52, not a logging one (every 10): metrics.jsonl holds the step anyway.
    rows = [json.loads(line) for line in (tmp_path / "whole" / "metrics.jsonl").read_text().splitlines()]
    assert [(r["iteration"], r["mask_dropped"]) for r in rows if "mask_dropped" in r] == [
        (52, scene.model.num_gaussians + 50 - models["whole"].num_gaussians)]
    assert models["resumed"].num_gaussians == models["whole"].num_gaussians
    for key, value in models["whole"].params.items():
        assert torch.equal(value, models["resumed"].params[key]), key


def test_a_rate_aware_window_that_density_control_or_compaction_could_edit_is_refused_before_training(scene, tmp_path):
    """The mask keeps a logit per row, so a run in which something else may remove Gaussians inside the window is
    refused when the trainer is built (not hours later, when the rows first change), naming what overlaps."""
    from stgc.compaction import CompactionConfig
    from stgc.train.config import FloaterConfig

    dataset = open_dataset(scene.root)
    start = STGModel.from_ply_arrays(scene.model.to_ply_arrays(), "lite", None, scene_extent=3.3)
    config = _config(50, iterations=100)
    config = dataclasses.replace(config, quantization_aware=dataclasses.replace(
        config.quantization_aware, rate_weight=1e-3, mask=True))
    Trainer(dataset, None, None, config, None, tmp_path / "fine", model=start)  # nothing else edits rows: accepted
    # The floater rules stop where the window starts (resolve_schedule), so they never overlap it.
    floaters = dataclasses.replace(config, floaters=FloaterConfig(near_camera=0.3))
    trainer = Trainer(dataset, None, None, floaters, None, tmp_path / "floaters", model=start)
    assert trainer.schedule.floaters_until == 50
    early = dataclasses.replace(config, schedule_scale=0.01)  # low-opacity pruning until iteration 70
    with pytest.raises(ValueError, match=r"overlaps low-opacity pruning \(until iteration 70;"):
        Trainer(dataset, None, None, early, None, tmp_path / "early", model=start)
    with pytest.raises(ValueError, match=r"overlaps ST-KNN compaction \(it prunes until iteration 99;"):
        Trainer(dataset, None, None, config, CompactionConfig(method="st-knn", case=0, window_start=0.3,
                                                              window_end=1.0), tmp_path / "stknn", model=start)
    # Pruning that ends before the window (Case 1: iterations 20-39 of 100) leaves the mask's rows alone.
    Trainer(dataset, None, None, config, CompactionConfig(method="st-knn", case=1), tmp_path / "case1", model=start)
    # Refused before the run's folder is written: the corrected command found "already holds a run".
    assert not (tmp_path / "early").exists() and not (tmp_path / "stknn").exists()
    # Without the mask the rows may change, but the compaction's probe renders the float model while the window
    # trains the quantized one: its damage budget would hold for another model than the one it prunes.
    simulated = dataclasses.replace(config, quantization_aware=dataclasses.replace(config.quantization_aware,
                                                                                   mask=False))
    Trainer(dataset, None, None, dataclasses.replace(simulated, schedule_scale=0.01), None, tmp_path / "rounds",
            model=start)  # density control may edit rows under a window without the mask
    with pytest.raises(ValueError, match=r"train.quantization_aware: the rate-aware window \(iterations 51-100\) "
                                         r"overlaps ST-KNN compaction .*: the compaction's renders .* would measure "
                                         r"the float model"):
        Trainer(dataset, None, None, simulated, CompactionConfig(method="st-knn", case=0, window_start=0.3,
                                                                 window_end=1.0), tmp_path / "stknn2", model=start)
    # The paper's rule reads the training loss, which the window renders quantized, and renders nothing else.
    from stgc.compaction.config import PAPER_RULE

    paper = CompactionConfig(method="st-knn", case=0, window_start=0.3, window_end=1.0, prune_trials=0, **PAPER_RULE)
    Trainer(dataset, None, None, simulated, paper, tmp_path / "paper", model=start)
    Trainer(dataset, None, None, simulated, CompactionConfig(method="st-knn", case=1), tmp_path / "case1b",
            model=start)


def test_the_straight_through_gradient_of_a_rotation_stored_with_its_sign_flipped_still_descends():
    from scenes import ring_camera, scene_model

    from stgc.train.quantization import QuantizationSimulation

    # The codec stores (q, omega) with q's largest component positive; half of these rotations have it negative.
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    model = scene_model()
    n = model.num_gaussians
    target = torch.from_numpy(rng.normal(size=(n, 4))).float()
    target = target / target.norm(dim=1, keepdim=True)
    target = torch.where(target.gather(1, target.abs().argmax(1, keepdim=True)) < 0, -target, target)
    flipped = torch.zeros(n, dtype=torch.bool)
    flipped[::2] = True
    with torch.no_grad():
        model.params["scaling"][:] = torch.log(torch.tensor([0.12, 0.02, 0.05]))
        start = (target + 0.15 * torch.randn(n, 4)) * 2.0  # not unit length either
        model.params["rotation"][:] = torch.where(flipped[:, None], -start, start)
        model.params["omega"][:] = 0.3 * torch.randn(n, 4)
    raw = model.params["rotation"].detach()
    flipped = raw.gather(1, raw.abs().argmax(1, keepdim=True))[:, 0] < 0  # the rows the codec stores negated
    assert 0.3 < float(flipped.float().mean()) < 0.7
    camera = ring_camera("0", 0.3, 0, 64, 48)
    background = torch.zeros(3)
    with torch.no_grad(), model.params_replaced({**model.params, "rotation": target}):
        truth = model.render(camera, t=0.9, background=background, backend="torch").rgb

    def gradients(params):
        for p in model.params.values():
            p.grad = None
        with model.params_replaced(params):
            rendered = model.render(camera, t=0.9, background=background, backend="torch").rgb
        ((rendered - truth) ** 2).mean().backward()
        return {k: model.params[k].grad.clone() for k in ("rotation", "omega")}

    exact = gradients(None)
    simulation = QuantizationSimulation(QuantizationAwareConfig(iterations=1, quality=5, allocation="ladder"))
    seen, _ = simulation.quantized_params(model)
    through = gradients(seen)
    with torch.no_grad():  # what the forward pass sees renders as the decoded model does: the same rotation
        assert torch.allclose(seen["rotation"], model.params["rotation"], atol=0.05)
    for key in ("rotation", "omega"):
        has = exact[key].norm(dim=1) > 1e-9
        cosine = torch.nn.functional.cosine_similarity(exact[key], through[key], dim=1)
        # Once -0.98 on the flipped rows: every step went uphill there.
        assert cosine[has & flipped].mean() > 0.9 and cosine[has & ~flipped].mean() > 0.9, key


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    """For bookkeeping only: each optimised allocation renders its views about a hundred times."""
    return write_panoptic_scene(tmp_path_factory.mktemp("qat-small"), views=4, frames=2, width=32, height=24)


def test_a_fine_tuning_of_a_rate_aware_run_opens_its_own_window(small_scene, tmp_path, monkeypatch):
    import stgc.train.quantization as quantization
    from stgc.cli import main

    scene = small_scene
    qualities = []
    real = quantization.optimise_on_views
    monkeypatch.setattr(quantization, "optimise_on_views", lambda *a, **k: qualities.append(a[2]) or real(*a, **k))
    common = ["--set", "train.progress=false", "--set", "train.tensorboard=false", "--set", "train.eval_at_end=false"]
    assert main(["train", str(scene.root), "--out", str(tmp_path / "a"), "--set", "train.iterations=20",
                 "--set", "train.schedule_scale=0.01", "--set", "data.init_source=random",
                 "--set", "data.max_points_per_frame=300",
                 "--set", "train.densify.enabled=false", "--set", "train.densify.prune_until=0", *common]) == 0

    def finetune(source: str, out: str, quality: int) -> dict:
        assert main(["finetune", str(tmp_path / source), "--out", str(tmp_path / out), "--iterations", "6",
                     "--set", "train.quantization_aware.iterations=6",
                     "--set", f"train.quantization_aware.quality={quality}",
                     "--set", "train.quantization_aware.rate_weight=0.001",
                     "--set", "train.quantization_aware.mask=true", *common]) == 0
        return torch.load(tmp_path / out / "checkpoint.pt", weights_only=False)["quantization_aware"]

    first = finetune("a", "b", 2)
    second = finetune("b", "c", 1)
    # Each window measured its own depths at its own quality, when it opened and when its mask settled (the second
    # once reused the first's, for q2), and each learned and settled its own mask (the second once had none).
    assert qualities == [2, 2, 1, 1]
    assert first["mask_settled"] and second["mask_settled"]
    assert second["allocation"] != first["allocation"]


def test_a_zero_quaternion_gets_no_rate_gradient():
    """1/|q| gave a zero rotation (official error-guided points) a rate gradient of about 1e12."""
    from stgc.codec.format import quantized_groups
    from stgc.codec.synthetic import synthetic_model
    from stgc.train.quantization import _visible

    arrays, decoder = synthetic_model(500, seed=3)
    model = STGModel.from_ply_arrays(arrays, "full", decoder, scene_extent=3.0)
    keep = _visible(model)
    zero = np.flatnonzero(keep)[:3]
    with torch.no_grad():
        model.params["rotation"][torch.from_numpy(zero)] = 0.0
    groups = quantized_groups({k: v[keep] for k, v in model.to_ply_arrays().items()}, "full", QUALITY)
    RateTerm.bits_per_gaussian(model, keep, groups).backward()
    grad = model.params["rotation"].grad
    assert torch.isfinite(grad).all() and float(grad[torch.from_numpy(zero)].abs().max()) == 0.0
    assert float(grad.abs().max()) > 0  # the other rows still have one


def test_the_window_renders_what_the_codec_decodes_at_the_measured_depths_and_leaves_unseen_rows_alone():
    """Row for row against the real encoder and decoder, with depths and step scales an optimised allocation would
    give, on a model with Gaussians no frame shows: the quantizers are fitted on the visible rows only (as
    `compress_run` stores them) and the window's depths are the ones measured, not the ladder's. Neither was seen by a
    test: the scenes above have no invisible Gaussian, and their optimised runs compared the simulation with itself."""
    from stgc.codec.format import canonical_rotation, decode, encode
    from stgc.codec.synthetic import synthetic_model
    from stgc.model.stg import ply_columns
    from stgc.train.quantization import QuantizationSimulation, _visible

    arrays, decoder = synthetic_model(3000, seed=3)
    model = STGModel.from_ply_arrays(arrays, "full", decoder, scene_extent=3.0)
    keep = _visible(model)
    assert 0 < int((~keep).sum()) < 200
    simulation = QuantizationSimulation(QuantizationAwareConfig(iterations=1, quality=3, allocation="optimised"))
    simulation.settings = ({"MOTN": 6, "FDC_": 5}, {"FDC_": [1.0, 1.5, 2.0, 1.0, 1.0, 1.0], "ROTN": [1.0, 2.0, 1.5]})
    seen, _ = simulation.quantized_params(model)
    columns = {name: seen[key].detach().numpy()[:, i]
               for key, names in ply_columns("full").items() for i, name in enumerate(names)}
    for key, param in model.params.items():
        assert torch.equal(seen[key][torch.from_numpy(~keep)], param[torch.from_numpy(~keep)]), key

    visible = {k: v[keep] for k, v in model.to_ply_arrays().items()}
    decoded = decode(encode(visible, "full", model.decoder_state(), 3, group_bits=simulation.settings[0],
                            step_scales=simulation.settings[1])).arrays
    rendered = {name: values[keep].astype(np.float64) for name, values in columns.items()}
    rotation, omega = canonical_rotation(np.stack([rendered[f"rot_{i}"] for i in range(4)], 1),
                                         np.stack([rendered[f"omega_{i}"] for i in range(4)], 1))
    rendered.update({f"rot_{i}": rotation[:, i] for i in range(4)} | {f"omega_{i}": omega[:, i] for i in range(4)})

    def by_position(table):  # the decoder's rows are in Morton order
        order = np.lexsort([np.round(np.asarray(table[c], np.float64), 5) for c in ("z", "y", "x")])
        return {name: np.asarray(values, np.float64)[order] for name, values in table.items()}

    rendered, decoded = by_position(rendered), by_position(decoded)
    # (q, omega) and (-q, -omega) are one rotation; which sign is canonical flips where two components of q are
    # equal in magnitude up to float32 rounding.
    sign = np.sign(sum(rendered[f"rot_{i}"] * decoded[f"rot_{i}"] for i in range(4)))
    assert np.mean(sign < 0) < 0.01
    for name in columns:
        if name.startswith("n"):  # normals: not stored
            continue
        aligned = rendered[name] * sign if name.startswith(("rot_", "omega_")) else rendered[name]
        assert np.allclose(aligned, decoded[name], rtol=1e-5, atol=1e-6), name
