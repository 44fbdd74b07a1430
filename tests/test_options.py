"""A new run's options (`stgc.options.resolve_configs`: `stgc train`, and every run of `stgc experiment`): options of
a part of training the run switches off are refused where they are given, and train.preset comes from --preset."""

from __future__ import annotations

import pytest

from stgc.cli import main
from stgc.config import ConfigError
from stgc.experiment.plans import load_plan_toml
from stgc.experiment.runner import check_plan_options
from stgc.options import resolve_configs

# Clone/split's own options, each with a value other than its default (stgc.options.CLONE_SPLIT_OPTIONS).
CLONE_SPLIT_VALUES = {"rounds": "3", "grad_threshold": "1e-4", "percent_dense": "0.02", "split_count": "3",
                      "max_gaussians": "100", "max_growth": "3", "prune_in_rounds": "true", "stats_views": "last",
                      "stats_count": "in_frustum"}


@pytest.mark.parametrize("sets, refused", [
    ({"train.ems.start": "100"}, "train.ems.start: given for a run without error-guided sampling"),
    ({"train.ems.enabled": "false", "train.ems.max_events": "3", "train.ems.patch": "8"},
     "train.ems.max_events, train.ems.patch: given for a run without error-guided sampling"),
    *(({"train.densify.enabled": "false", f"train.densify.{name}": CLONE_SPLIT_VALUES[name]},
       f"train.densify.{name}: acts only in clone/split rounds") for name in CLONE_SPLIT_VALUES),
    ({"data.preprocess_fraction": "0.5"}, "data.preprocess_fraction: given for a run whose data.preprocess is none"),
    ({"model.variant": "lite", "train.lr.decoder": "0.1"}, "train.lr.decoder: the lite model has no decoder"),
    ({"model.variant": "lite", "train.lr.features_t": "0.1"}, "train.lr.features_t: the lite model"),
    ({"compaction.method": "st-knn", "train.densify.opacity_reset_interval": "0",
      "compaction.reset_settle_steps": "5"}, "compaction.reset_settle_steps: waits after an opacity reset"),
    # The cpu preset resets at 900 and 1,800 of 9,000 iterations (interval 30): a custom window that ends before the
    # first, and one that starts 900 iterations after the last, where 5 steps' wait ends 150 iterations after it.
    ({"compaction.method": "st-knn", "compaction.case": "0", "compaction.window_start": "0.01",
      "compaction.window_end": "0.09", "compaction.reset_settle_steps": "5"},
     "no pruning step comes within 5 steps after one"),
    ({"compaction.method": "st-knn", "compaction.case": "0", "compaction.window_start": "0.3",
      "compaction.window_end": "0.5", "compaction.reset_settle_steps": "5"}, "resets at 900, 1800"),
])
def test_options_of_a_part_of_training_that_is_switched_off_are_refused(sets, refused):
    """They were recorded in config.json and ignored: EMS options without EMS, clone/split options without
    densification, a lite model's decoder and time-feature rates, a preprocessing fraction without preprocessing."""
    with pytest.raises(ConfigError) as caught:
        resolve_configs("cpu", {}, {}, sets)
    assert refused in str(caught.value)


def test_they_are_refused_from_every_layer_that_gives_them(tmp_path, capsys):
    with pytest.raises(ConfigError, match="train.lr.features_t: the lite model"):
        resolve_configs("cpu", {"model": {"variant": "lite"}}, {"train": {"lr.features_t": "0.2"}}, {})
    run = tmp_path / "run"
    assert main(["train", str(tmp_path), "--out", str(run), "--variant", "lite", "--set", "train.lr.decoder=0.1"]) == 2
    assert "train.lr.decoder: the lite model has no decoder" in capsys.readouterr().err and not run.exists()
    assert main(["train", str(tmp_path), "--out", str(run), "--train.densify.enabled", "false",
                 "--train.densify.grad_threshold", "1e-4"]) == 2
    assert "train.densify.grad_threshold: acts only in clone/split rounds" in capsys.readouterr().err
    assert not run.exists()


@pytest.mark.parametrize("preset, sets", [
    ("cpu", {"train.ems.enabled": "true", "train.ems.start": "100", "train.ems.max_events": "3"}),
    # Pruning, the floater rules and the opacity resets act at the densification steps without clone/split.
    ("cpu", {"train.densify.enabled": "false", "train.densify.interval": "100", "train.densify.start": "10",
             "train.densify.prune_opacity": "0.01", "train.densify.prune_until": "500",
             "train.densify.opacity_reset_interval": "100", "train.densify.opacity_reset_value": "0.02"}),
    ("cpu", {f"train.densify.{name}": value for name, value in CLONE_SPLIT_VALUES.items()}),
    ("cpu", {"data.preprocess": "stg-isolated", "data.preprocess_fraction": "0.5"}),
    ("cpu", {"train.lr.decoder": "0.1", "train.lr.features_t": "0.1"}),
    ("cpu", {"model.variant": "lite", "train.lr.features_dc": "0.01"}),
    ("cpu", {"compaction.method": "st-knn", "compaction.reset_settle_steps": "5"}),
    # No wait is what a run without resets does: a plan that pins it stays valid when the resets are switched off.
    ("cpu", {"compaction.method": "st-knn", "compaction.reset_settle_steps": "0",
             "train.densify.opacity_reset_interval": "0"}),
    # A window that ends at the first reset (900) still settles after it; one that starts within the wait after the
    # last (1,800 + 5 x 30) too.
    ("cpu", {"compaction.method": "st-knn", "compaction.case": "0", "compaction.window_start": "0.21",
             "compaction.window_end": "0.5", "compaction.reset_settle_steps": "5"}),
    ("cpu", {"compaction.method": "st-knn", "compaction.case": "0", "compaction.window_start": "0.01",
             "compaction.window_end": "0.101", "compaction.reset_settle_steps": "5"}),
    # The paper preset's own clone/split option (stats_views last) is no option given.
    ("paper", {"train.densify.enabled": "false"}),
])
def test_the_same_options_where_they_act_and_a_preset_s_own_values_are_accepted(preset, sets):
    resolve_configs(preset, {}, {}, sets)


def test_train_preset_is_set_by_the_preset_only(tmp_path, capsys):
    """`--preset paper --set train.preset=cpu` recorded a paper-schedule run as 'cpu'."""
    assert resolve_configs("paper", {}, {}, {})["train"].preset == "paper"
    for options, sets in (({}, {"train.preset": "cpu"}), ({"train": {"preset": "paper"}}, {}),
                          ({}, {"train.preset": "anything"})):
        with pytest.raises(ConfigError, match="train.preset: set by the preset a run starts from"):
            resolve_configs("paper", {}, options, sets)
    run = tmp_path / "run"
    for flag in (["--set", "train.preset=cpu"], ["--train.preset", "cpu"]):
        assert main(["train", str(tmp_path), "--out", str(run), "--preset", "paper", *flag]) == 2
        assert "train.preset: set by the preset a run starts from (--preset" in capsys.readouterr().err
        assert not run.exists()


PLAN = """
name = "p"
[[runs]]
name = "stg"
family = "STG"
overrides = { "compaction.method" = "none", "train.densify.enabled" = false }
"""


def test_an_experiment_refuses_them_too(tmp_path):
    """`stgc experiment` checks every run's options before its first training (check_plan_options): a plan entry's
    and --set's options that act on nothing there were recorded in its runs' config.json."""
    path = tmp_path / "plan.toml"
    path.write_text(PLAN)
    plan = load_plan_toml(path)
    check_plan_options(plan, "cpu", {}, tmp_path)
    # --set's: refused for the run (or, where the runner leaves them out of the runs they act nothing in, as it does
    # compaction options, refused as acting in no run of the plan).
    with pytest.raises(ConfigError, match="train.densify.grad_threshold: acts (only in clone/split|on nothing)"):
        check_plan_options(plan, "cpu", {"train.densify.grad_threshold": "1e-4"}, tmp_path)
    with pytest.raises(ConfigError, match="train.ems.start: (given for a run without error-guided|acts on nothing)"):
        check_plan_options(plan, "cpu", {"train.ems.start": "100"}, tmp_path)
    with pytest.raises(ConfigError, match="train.preset: set by the preset"):
        check_plan_options(plan, "paper", {"train.preset": "cpu"}, tmp_path)
    path.write_text(PLAN.replace("false }", 'false, "data.preprocess_fraction" = 0.5 }'))
    with pytest.raises(ConfigError, match="run 'stg'.*data.preprocess_fraction: given for a run whose"):
        check_plan_options(load_plan_toml(path), "cpu", {}, tmp_path)
