"""Foreground masks: reading them, and initial points for the subjects from their visual hull."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image
from scenes import BALL_CENTRE, BALL_RADIUS, write_panoptic_scene

from stgc.data import open_dataset
from stgc.data.points import initial_points, mask_hull_points
from stgc.errors import DataError


@pytest.fixture(scope="module")
def masked_scene(tmp_path_factory):
    return write_panoptic_scene(tmp_path_factory.mktemp("masked"), views=12, frames=2, width=64, height=48,
                                masks=True)


def test_hull_points_lie_inside_the_known_object(masked_scene):
    dataset = open_dataset(masked_scene.root)
    assert dataset.has_masks
    xyz, rgb = mask_hull_points(dataset, 0, 500, np.random.default_rng(0), resolution=64)
    assert len(xyz) > 100
    distance = np.linalg.norm(xyz - BALL_CENTRE, axis=1)
    # The hull of 11 views encloses the ball tightly: every point within a voxel diagonal and a pixel of slack.
    voxel = 2 * 3.0 / 64  # the viewing radius is the ring's 3 units
    assert distance.max() < BALL_RADIUS + 1.5 * voxel
    assert np.median(distance) < BALL_RADIUS
    # Coloured from the ball's foreground pixels: red (0.9, 0.2, 0.1) blended with the grey shell behind it.
    assert rgb[:, 0].mean() > rgb[:, 2].mean() + 0.15


def test_initial_points_add_the_hull_only_where_masks_exist(masked_scene, tmp_path):
    dataset = open_dataset(masked_scene.root)
    plain = initial_points(dataset, source="random", random_points_per_frame=50)
    with_hull = initial_points(dataset, source="random", random_points_per_frame=50, mask_points_per_frame=80)
    assert len(with_hull) == len(plain) + 2 * 80


def test_mask_of_the_wrong_size_is_an_error_naming_the_file(masked_scene, tmp_path):
    import shutil

    root = tmp_path / "scene"
    shutil.copytree(masked_scene.root, root)
    bad = root / "seg" / "1" / "000000.png"
    Image.fromarray(np.zeros((10, 13), np.uint8)).save(bad)
    dataset = open_dataset(root)
    camera = next(c for c in dataset.train if c.name == "1" and c.frame == 0)
    with pytest.raises(DataError, match="mask is 13x10") as err:
        dataset.load_mask(camera)
    assert str(bad) in str(err.value)
    bad.write_bytes(b"not a png")
    with pytest.raises(DataError, match="unreadable mask"):
        dataset.load_mask(camera)


def _mask_and_full_size_mask(masked_scene, downscale: float) -> tuple[np.ndarray, np.ndarray]:
    """Camera 1's frame-0 mask at `downscale` (checked to have its camera's size) and at the full size."""
    masks = []
    for factor in (downscale, 1):
        dataset = open_dataset(masked_scene.root, downscale=factor)
        camera = next(c for c in dataset.train if c.name == "1" and c.frame == 0)
        mask = dataset.load_mask(camera)
        assert mask is not None and mask.shape == (camera.height, camera.width)
        masks.append(mask)
    return masks[0], masks[1]


def test_masks_follow_a_downscale_that_is_not_whole(masked_scene):
    """At --data.downscale 1.5 the images are 43x32 (64x48 / 1.5): each mask is averaged over the same boxes, and
    agrees with the full-size mask sampled at the small pixels' centres (they were refused)."""
    mask, reference = _mask_and_full_size_mask(masked_scene, 1.5)
    assert mask.shape == (32, 43)
    rows = np.minimum(((np.arange(32) + 0.5) * 48 / 32).astype(int), 47)
    cols = np.minimum(((np.arange(43) + 0.5) * 64 / 43).astype(int), 63)
    sampled = reference[rows][:, cols]
    assert 0.05 < sampled.mean() < 0.95  # the ball is in view: a comparison that can fail
    assert (mask == sampled).mean() > 0.95


def test_masks_follow_a_downscale_below_one(masked_scene):
    """At --data.downscale 0.5 the images are enlarged to 128x96: the full-size mask is enlarged with them (it was
    refused as a file of the wrong size). Enlarged and thresholded, it agrees with the mask sampled at the large
    pixels' centres except along the edge."""
    mask, reference = _mask_and_full_size_mask(masked_scene, 0.5)
    assert mask.shape == (96, 128)
    sampled = np.repeat(np.repeat(reference, 2, axis=0), 2, axis=1)
    assert 0.05 < sampled.mean() < 0.95  # the ball is in view: a comparison that can fail
    assert (mask == sampled).mean() > 0.97
    assert abs(int(mask.sum()) - int(sampled.sum())) < 0.05 * sampled.sum()  # the edge neither grows nor shrinks


def test_a_static_cloud_for_the_first_frame_leaves_every_frame_its_hull_points(masked_scene, tmp_path):
    import shutil

    root = tmp_path / "scene"
    shutil.copytree(masked_scene.root, root)
    # Dynamic 3D Gaussians' release: init_pt_cld.npz holds one static cloud (x, y, z, r, g, b, seg).
    static = np.random.default_rng(0).uniform(-1, 1, (300, 7))
    np.savez(root / "init_pt_cld.npz", data=static)
    dataset = open_dataset(root)
    cloud = initial_points(dataset, source="data", mask_points_per_frame=80)
    counts = cloud.counts_per_time()
    # Frame 1 has no shipped points, but still its hull points (they were skipped with its missing cloud).
    assert counts == {0.0: 300 + 80, 0.5: 80}


def test_every_segment_of_a_video_starts_from_the_static_cloud(masked_scene, tmp_path):
    import shutil

    root = tmp_path / "scene"
    shutil.copytree(masked_scene.root, root)
    static = np.random.default_rng(0).uniform(-1, 1, (300, 7))
    np.savez(root / "init_pt_cld.npz", data=static)
    # The second segment (frame 1 on): the capture's cloud at its own first frame, not only its hull points.
    segment = open_dataset(root, start=1, duration=1)
    cloud = initial_points(segment, source="data", mask_points_per_frame=80)
    assert cloud.counts_per_time() == {0.0: 300 + 80}


def _rewrite_masks(root, write) -> None:
    """Every mask of the scene at `root` stored again by `write(foreground bool [H, W], path)`."""
    for path in sorted((root / "seg").rglob("*.png")):
        write(np.asarray(Image.open(path)) > 0, path)


def _as_palette(foreground, path) -> None:
    image = Image.fromarray(foreground.astype(np.uint8), mode="P")
    image.putpalette([0, 0, 0, 128, 0, 0] + [0] * 762)  # DAVIS: index 1 is dark red, grey level 38
    image.save(path)


def _as_grey_palette_white_first(foreground, path) -> None:
    """A black and white mask as Pillow's quantize may store it: white at index 0, read by its grey level."""
    image = Image.fromarray((~foreground).astype(np.uint8), mode="P")
    image.putpalette([255, 255, 255, 0, 0, 0] + [0] * 762)
    image.save(path)


@pytest.mark.parametrize("write", [
    pytest.param(lambda fg, path: Image.fromarray(fg.astype(np.uint8)).save(path), id="0-1-grey"),
    pytest.param(_as_palette, id="palette-dark-index-1"),
    pytest.param(_as_grey_palette_white_first, id="grey-palette-white-index-0"),
    pytest.param(lambda fg, path: Image.fromarray(fg.astype(np.uint8) * 255).quantize(2).save(path),
                 id="pillow-quantize"),
    pytest.param(lambda fg, path: Image.fromarray(fg).convert("1").save(path), id="1-bit"),
    pytest.param(lambda fg, path: Image.fromarray(fg.astype(np.uint8) * 255).save(path), id="0-255-grey"),
])
def test_masks_stored_as_0_1_or_palette_images_read_as_their_foreground(masked_scene, tmp_path, write):
    """A 0/1 greyscale mask (Dynamic 3D Gaussians' seg values) and a palette mask whose foreground index has a dark
    colour were read through their grey level: every pixel below 128, all background, and the visual hull empty
    with only an INFO line. 0/255 and 1-bit masks read as before."""
    import shutil

    root = tmp_path / "scene"
    shutil.copytree(masked_scene.root, root)
    reference = open_dataset(masked_scene.root)
    _rewrite_masks(root, write)
    dataset = open_dataset(root)
    for camera, original in zip(dataset.train_at(0), reference.train_at(0)):
        mask, expected = dataset.load_mask(camera), reference.load_mask(original)
        assert mask is not None and expected is not None and expected.any()
        assert np.array_equal(mask, expected), camera.name
    # Downscaled, the 0/1 and palette masks are averaged as the 0/255 ones are.
    small, small_reference = open_dataset(root, downscale=2), open_dataset(masked_scene.root, downscale=2)
    camera = small.train_at(0)[0]
    assert np.array_equal(small.load_mask(camera), small_reference.load_mask(small_reference.train_at(0)[0]))
    xyz, _ = mask_hull_points(dataset, 0, 500, np.random.default_rng(0), resolution=48)
    assert len(xyz) > 100


def test_masks_that_are_all_background_are_warned_about_once(masked_scene, tmp_path, caplog):
    """Masks that read as all background (the wrong encoding, or an empty export) left the visual hull empty with
    only an INFO line per frame: the run trained without the subjects' points and said nothing of it."""
    import shutil

    root = tmp_path / "scene"
    shutil.copytree(masked_scene.root, root)
    _rewrite_masks(root, lambda fg, path: Image.fromarray(np.zeros(fg.shape, np.uint8)).save(path))
    dataset = open_dataset(root)
    with caplog.at_level("WARNING", logger="stgc.data.points"):
        initial_points(dataset, source="random", random_points_per_frame=50, mask_points_per_frame=80)
    said = [r for r in caplog.records if "mask at frame" in r.getMessage()]
    assert len(said) == 1 and "is empty (all background" in said[0].getMessage()  # two frames, said once
    caplog.clear()
    with caplog.at_level("WARNING", logger="stgc.data.points"):
        initial_points(open_dataset(masked_scene.root), source="random", random_points_per_frame=50,
                       mask_points_per_frame=80)
    assert not [r for r in caplog.records if "mask at frame" in r.getMessage()]


def test_masks_are_used_when_only_the_first_training_view_has_none(masked_scene, tmp_path, caplog):
    """`has_masks` looked at the first training view alone: without its mask, the other views' masks were all
    ignored, silently (no hull points, no mask term), where the docs promise the view is left out and said so."""
    import shutil

    root = tmp_path / "scene"
    shutil.copytree(masked_scene.root, root)
    first = open_dataset(root).train[0].name
    shutil.rmtree(root / "seg" / first)
    dataset = open_dataset(root)
    assert dataset.has_masks
    with caplog.at_level("WARNING", logger="stgc.data.points"):
        cloud = initial_points(dataset, source="random", random_points_per_frame=50, mask_points_per_frame=80)
    assert len(cloud) == 2 * (50 + 80)
    assert f"training views {first} have no foreground mask" in caplog.text
    shutil.rmtree(root / "seg")
    assert not open_dataset(root).has_masks
