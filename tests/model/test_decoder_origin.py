"""A decoder that ignores the ray origin: colours cannot depend on which camera looks, and the files stay official."""

from __future__ import annotations

import numpy as np
import torch

from stgc.model.decoder import RAY_ORIGIN_INPUTS, SandwichDecoder


def _inputs(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    features = torch.rand(4, 5, 9, generator=g)
    direction = torch.nn.functional.normalize(torch.randn(4, 5, 3, generator=g), dim=-1)
    return features, direction


def test_ignoring_the_origin_makes_colour_independent_of_the_camera_position_and_survives_training():
    decoder = SandwichDecoder(generator=torch.Generator().manual_seed(1))
    features, direction = _inputs()
    here = torch.cat([torch.zeros(4, 5, 3), direction], -1)
    there = torch.cat([torch.full((4, 5, 3), 7.0), direction], -1)
    assert not torch.allclose(decoder(features, here), decoder(features, there))  # official: it depends
    decoder.ignore_ray_inputs(origin=True)
    optimizer = torch.optim.Adam(decoder.parameters(), lr=0.1)
    for _ in range(5):  # gradients through the origin columns are masked, so they stay zero
        loss = (decoder(features, there) - 0.3).square().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert not decoder.uses_ray_origin
    assert torch.equal(decoder.mlp1.weight[:, RAY_ORIGIN_INPUTS], torch.zeros(6, 3, 1, 1))
    torch.testing.assert_close(decoder(features, here), decoder(features, there), rtol=0, atol=0)
    # The direction still matters: view-dependent colour is kept.
    turned = torch.cat([torch.zeros(4, 5, 3), -direction], -1)
    assert not torch.allclose(decoder(features, here), decoder(features, turned))
    # A state_dict loaded into a fresh (official) decoder renders the same: nothing outside the weights changed.
    official = SandwichDecoder()
    official.load_state_dict(decoder.state_dict())
    np.testing.assert_array_equal(official(features, there).detach().numpy(), decoder(features, there).detach().numpy())


def test_ignoring_the_direction_too_makes_colour_the_same_from_every_camera_and_survives_training():
    decoder = SandwichDecoder(generator=torch.Generator().manual_seed(2))
    features, direction = _inputs(1)
    here = torch.cat([torch.zeros(4, 5, 3), direction], -1)
    elsewhere = torch.cat([torch.full((4, 5, 3), -3.0), -direction.flip(-1)], -1)
    assert not torch.allclose(decoder(features, here), decoder(features, elsewhere))
    decoder.ignore_ray_inputs(origin=True)
    decoder.ignore_ray_inputs(direction=True)  # a second call adds to the first
    # The specular and time features still reach the colour.
    moved = features.clone()
    moved[..., 3:9] += 0.5
    assert not torch.allclose(decoder(features, here), decoder(moved, here))
    optimizer = torch.optim.Adam(decoder.parameters(), lr=0.1)
    for _ in range(5):
        loss = (decoder(features, elsewhere) - 0.7).square().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    assert not decoder.uses_ray_origin and not decoder.uses_ray_direction
    torch.testing.assert_close(decoder(features, here), decoder(features, elsewhere), rtol=0, atol=0)


def test_the_direction_alone_can_be_ignored():
    decoder = SandwichDecoder(generator=torch.Generator().manual_seed(3))
    decoder.ignore_ray_inputs(direction=True)
    assert decoder.uses_ray_origin and not decoder.uses_ray_direction
