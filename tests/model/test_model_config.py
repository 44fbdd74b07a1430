"""ModelConfig refuses values the trainer would read as something else."""

from __future__ import annotations

import pytest

from stgc.model import ModelConfig


@pytest.mark.parametrize("name", ["decoder_ray_origin", "decoder_ray_direction"])
@pytest.mark.parametrize("value", ["On", "yes", True, None])
def test_a_decoder_ray_input_other_than_auto_on_or_off_is_refused(name, value):
    """The options were not checked: a Python caller's ModelConfig(decoder_ray_origin='On') (or True) was taken,
    and the trainer, which turns on only 'on' and 'auto', trained with the input off without a word."""
    with pytest.raises(ValueError, match=f"model.{name} must be one of \\('auto', 'on', 'off'\\), got {value!r}"):
        ModelConfig(**{name: value})
    for good in ("auto", "on", "off"):
        assert getattr(ModelConfig(**{name: good}), name) == good
