import numpy as np
import pytest
import torch

from enmi_torch.data import scene_change
from enmi_torch.data.scene_change import (
    CHANGES,
    illumination,
    occluders,
    resample_blur,
    shadows,
    smooth_field,
    tone,
    warp,
)

KINDS = list(CHANGES)


@pytest.fixture(scope="module")
def photograph() -> torch.Tensor:
    """A non-square crop of scikit-image's camera (CC0), float64 grey levels."""
    from skimage import data

    return torch.from_numpy(data.camera()[100:172, 200:296].astype(np.float64))


@pytest.mark.parametrize("kind", KINDS)
def test_strength_zero_is_the_identity(kind, photograph, dtype):
    image = photograph.to(dtype)
    assert torch.equal(CHANGES[kind](image, 7, 0.0), image)
    assert torch.equal(scene_change.scene_change(image, 7, 0.0), image)


@pytest.mark.parametrize("kind", KINDS)
def test_a_pure_function_of_image_seed_and_strength(kind, photograph, dtype):
    image = photograph.to(dtype)
    first = CHANGES[kind](image, 11, 0.6)
    assert first.shape == image.shape and first.dtype == dtype
    assert torch.equal(first, CHANGES[kind](image.clone(), 11, 0.6))
    assert not torch.equal(first, CHANGES[kind](image, 12, 0.6))
    assert torch.equal(image, photograph.to(dtype))  # the input is left alone


@pytest.mark.parametrize("kind", KINDS)
def test_float32_and_float64_agree(kind, photograph):
    wide = CHANGES[kind](photograph, 3, 0.8)
    narrow = CHANGES[kind](photograph.float(), 3, 0.8)
    torch.testing.assert_close(narrow.double(), wide, rtol=0, atol=2e-3)


@pytest.mark.parametrize("kind", KINDS)
def test_the_change_grows_with_strength(kind, photograph):
    sizes = []
    for strength in (0.2, 0.5, 1.0):
        sizes.append(
            np.mean([float((CHANGES[kind](photograph, seed, strength) - photograph).abs().mean()) for seed in range(4)])
        )
    assert 0 < sizes[0] < sizes[1] < sizes[2], sizes


@pytest.mark.parametrize("kind", ["illumination", "tone", "resample_blur", "warp"])
def test_continuous_changes_vanish_with_strength(kind, photograph):
    small = (CHANGES[kind](photograph, 5, 1e-5) - photograph).abs().max()
    assert 0 < small < 1.0


@pytest.mark.parametrize("kind", KINDS)
def test_values_stay_in_the_range(kind, photograph):
    image = 10 + photograph * (190 / 255)
    for seed in range(3):
        changed = CHANGES[kind](image, seed, 1.0, value_range=(10.0, 200.0))
        assert changed.min() >= 10 and changed.max() <= 200
    assert CHANGES[kind](photograph, 0, 1.0).max() <= 255


def test_smooth_field_is_standardised_and_smooth():
    field = smooth_field((50, 70), 16.0, torch.Generator().manual_seed(0))
    assert field.shape == (50, 70)
    assert abs(float(field.mean())) < 1e-12 and abs(float(field.std()) - 1) < 1e-12
    # Neighbouring pixels of a 16-pixel-wide field are nearly equal; white noise's differ by sqrt(2) std.
    assert float((field[:, 1:] - field[:, :-1]).std()) < 0.2
    assert float((field[1:] - field[:-1]).std()) < 0.2


def test_illumination_is_a_gain_of_the_stated_spread():
    image = torch.full((80, 120), 60.0, dtype=torch.float64)
    for strength in (0.4, 1.0):
        log_gain = (illumination(image, 2, strength) / image).log()
        assert abs(float(log_gain.std()) - 0.5 * strength) < 1e-9 and abs(float(log_gain.mean())) < 1e-9


def test_warp_moves_pixels_by_the_stated_amount_with_no_net_shift():
    # On a ramp 3 * column, the warp's output minus the image is 3 * the column displacement (away from borders).
    cols = torch.arange(200, dtype=torch.float64)
    image = (3 * cols)[None].expand(150, 200).clone()
    changed = warp(image, 4, 1.0, value_range=(0.0, 1000.0))
    shift = ((changed - image) / 3)[8:-8, 8:-8]
    assert abs(float(shift.mean())) < 0.1
    assert 0.9 * 1.2 < float(shift.std()) < 1.1 * 1.2
    rows = torch.arange(150, dtype=torch.float64)
    transposed = warp((3 * rows)[:, None].expand(150, 200).clone(), 4, 0.5, value_range=(0.0, 1000.0))
    assert 0.9 * 0.6 < float(((transposed - 3 * rows[:, None]) / 3)[8:-8, 8:-8].std()) < 1.1 * 0.6


def test_shadows_darken_the_stated_share_by_the_stated_factor():
    image = torch.full((90, 110), 200.0, dtype=torch.float64)
    for strength in (0.3, 1.0):
        ratio = shadows(image, 9, strength) / image
        assert abs(float(ratio.min()) - (1 - 0.3 - 0.4 * strength)) < 1e-9
        dark = float((ratio < 1 - 0.2 * (0.3 + 0.4 * strength)).double().mean())
        assert 0.3 * strength - 0.05 < dark < 0.3 * strength + 0.15


def test_occluders_cover_the_stated_share_with_other_texture():
    image = torch.full((90, 110), 128.0, dtype=torch.float64)
    for strength in (0.25, 1.0):
        covered = float((occluders(image, 6, strength) != 128.0).double().mean())
        assert 0.4 * strength <= covered < 0.4 * strength + 0.15
    changed = occluders(image, 6, 1.0)
    assert float(changed[changed != 128.0].std()) > 5  # textured, not flat paint


def test_tone_is_linear_in_strength_and_not_a_function_of_grey_level():
    # Each grey level appears all down a column.
    image = (torch.arange(128.0) * 2 % 256).double()[None].expand(96, 128).clone()
    full = tone(image, 8, 1.0)
    inside = (full > 0) & (full < 255)
    half = tone(image, 8, 0.5)
    torch.testing.assert_close(half[inside], 0.5 * image[inside] + 0.5 * full[inside], rtol=0, atol=1e-9)
    # The same grey level gets different values in different places: the two curves are blended in space.
    assert float(full.std(0).mean()) > 5
    assert float(tone(image, 8, 1.0).std(0).mean()) == float(full.std(0).mean())


def test_resample_blur_keeps_flat_images_and_removes_detail():
    flat = torch.full((40, 52), 77.0, dtype=torch.float64)
    torch.testing.assert_close(resample_blur(flat, 1, 1.0), flat, rtol=0, atol=1e-9)
    checker = ((torch.arange(40)[:, None] + torch.arange(52)[None]) % 2 * 200.0).double()
    detail = [float(resample_blur(checker, 1, s).diff(dim=1).abs().mean()) for s in (0.0, 0.3, 1.0)]
    assert detail[0] > detail[1] > detail[2]
    assert abs(float(resample_blur(checker, 1, 1.0).mean()) - 100) < 5


def test_scene_change_composes_in_a_fixed_order(photograph):
    kinds = ["tone", "warp", "occluders"]
    changed = scene_change.scene_change(photograph, 4, 0.5, kinds=kinds)
    assert torch.equal(changed, scene_change.scene_change(photograph, 4, 0.5, kinds=list(reversed(kinds))))
    assert not torch.equal(changed, scene_change.scene_change(photograph, 5, 0.5, kinds=kinds))
    assert torch.equal(scene_change.scene_change(photograph, 4, 0.5, kinds=[]), photograph)
    everything = scene_change.scene_change(photograph, 4, 0.5)
    assert float((everything - photograph).abs().mean()) > 1


@pytest.mark.parametrize(
    ("call", "error", "match"),
    [
        (lambda image: warp(image.numpy(), 0, 0.5), TypeError, "image must be a torch.Tensor"),
        (lambda image: warp(image.long(), 0, 0.5), TypeError, "image must be a floating-point"),
        (lambda image: warp(image[None], 0, 0.5), ValueError, r"image must be \(H, W\)"),
        (lambda image: warp(image[:1], 0, 0.5), ValueError, r"image must be \(H, W\)"),
        (lambda image: tone(image, 0, 1.5), ValueError, r"strength must be a number in \[0, 1\], got 1.5"),
        (lambda image: tone(image, 0, -0.1), ValueError, "strength must be"),
        (lambda image: tone(image, 0, True), ValueError, "strength must be"),
        (lambda image: tone(image, 0.5, 0.5), TypeError, "seed must be an int, got float"),
        (lambda image: shadows(image, 0, 0.5, value_range=(5, 5)), ValueError, "value_range must be finite"),
        (lambda image: scene_change.scene_change(image, 0, 0.5, kinds=["fog"]), ValueError, "kinds must be one of"),
        (lambda image: scene_change.scene_change(image, 0, 0.5, kinds="tone"), TypeError, "kinds must be a sequence"),
    ],
)
def test_bad_input_is_refused_with_a_clear_message(call, error, match, photograph):
    with pytest.raises(error, match=match):
        call(photograph)
