"""The official STG code's per-dataset training configs, in stgc's option names.

The official code trains every scene from a JSON config of its dataset family (`configs/n3d_*/`,
`configs/techni_*/`; ../shared/reference/stg_official_code.md has the table). Most of their values are the code's
own defaults, which stgc's options default to as well; the values below are the ones a family changes. A source
says which family its scenes belong to (`Dataset.official_config`); an option left unset (None) takes its
family's value, else the official default, and the run's config.json records the value it trained with.

Not carried over, because they depend on the scene or the variant rather than the dataset (the official configs
set them per scene): point preprocessing (`preprocesspoints`, `data.preprocess`), the second densification mode of
coffee_martini and flame_salmon_1 (with `scaling_lr` 0.003), the N3DV world-z < 4.5 cut and the test checkpoint.
Nor the image resolution (N3DV at half size, Technicolor at full): `data.downscale` is the user's.
"""

from __future__ import annotations

from typing import Any

# The official code's defaults for the options a family changes.
OFFICIAL_DEFAULTS: dict[str, Any] = {
    "train.lr.scaling": 5e-3,
    "model.trbf_scale_init": 0.0,  # minus --trbfslinit
    "model.decoder_activation": "sigmoid",  # 'sandwich'
}

# What each family's configs set instead. Technicolor's 12 clone/split rounds (`desicnt`) are for the dense
# per-frame COLMAP clouds its scenes ship; from a sparse cloud stgc's own schedule applies (DensifyConfig).
PER_FAMILY: dict[str, dict[str, Any]] = {
    "n3dv": {"train.lr.scaling": 1.5e-3},
    "technicolor": {"model.trbf_scale_init": -2.0, "model.decoder_activation": "clamp",  # 'sandwichnoact'
                    "train.densify.rounds": 12},
}
FAMILIES = tuple(PER_FAMILY)
# Every option (dotted, with its section) whose unset value the data's family decides.
FAMILY_OPTIONS = frozenset(OFFICIAL_DEFAULTS) | frozenset(key for values in PER_FAMILY.values() for key in values)


def family_options(prefix: str) -> tuple[str, ...]:
    """The names under `prefix` ("model.", "train.lr.") of the options the data's family decides."""
    return tuple(sorted(key.removeprefix(prefix) for key in FAMILY_OPTIONS
                        if key.startswith(prefix) and "." not in key.removeprefix(prefix)))


def official_value(option: str, family: str | None) -> Any:
    """The value the official configs of `family` (None: a source without one) train `option` with (dotted, with
    its section), or None where they leave it to stgc's own default."""
    if family is not None and family not in PER_FAMILY:
        raise ValueError(f"unknown official config family {family!r}; expected one of {FAMILIES}")
    return PER_FAMILY.get(family or "", {}).get(option, OFFICIAL_DEFAULTS.get(option))
