import numpy as np
import pytest
import torch

from enmi_torch.data import SyntheticPairs, gravel_texture, lidar_truth, make_truth, match_intensity, road_patch
from enmi_torch.variance import empirical_variance


def stack(pairs, count):
    items = [pairs[index] for index in range(count)]
    return tuple(torch.stack([item[key] for item in items]) for key in ("local", "prior", "valid"))


def test_pairs_are_a_function_of_seed_and_index():
    truth = lidar_truth((20, 20))
    first, again, other = SyntheticPairs(truth, 5, seed=1), SyntheticPairs(truth, 5, seed=1), SyntheticPairs(truth, 5)
    for key in ("local", "prior"):
        assert torch.equal(first[3][key], again[3][key])
        assert torch.equal(first[-2][key], first[3][key])
        assert not torch.equal(first[3][key], other[3][key])
        assert not torch.equal(first[3][key], first[2][key])
    assert first[3]["index"] == 3 and len(first) == 5
    with pytest.raises(IndexError, match="index"):
        first[5]


@pytest.mark.parametrize("flavour", ["lidar", "camera"])
def test_noise_has_the_truth_variance(flavour):
    truth = make_truth(flavour, (16, 16), 10.0)
    local, prior, valid = stack(SyntheticPairs(truth, 600, seed=2), 600)
    assert torch.equal(valid[0, 0], truth.valid) and bool((local[:, 0][:, ~truth.valid] == 0).all())
    variance, defined = empirical_variance(local, prior, valid)
    assert torch.equal(defined, truth.valid)
    ratio = variance[defined] / truth.variance[defined]
    # 600 pairs: each pixel's estimate has a relative std of sqrt(2 / 599) = 5.8 %.
    assert float((ratio - 1).square().mean().sqrt()) == pytest.approx(np.sqrt(2 / 599), rel=0.15)
    mean_residual = (local - prior)[valid].mean()
    assert abs(float(mean_residual)) < 0.1


def test_road_patch_is_gravel_with_lane_markings():
    texture = gravel_texture()
    assert texture.shape == (512, 512) and texture.dtype == np.float32 and not texture.flags.writeable
    patches = [road_patch(np.random.default_rng(seed), (64, 48)) for seed in range(20)]
    for patch in patches:
        assert patch.shape == (64, 48) and patch.dtype == np.float32
        assert 0 <= patch.min() and patch.max() <= 255
    # Painted markings are brighter than almost all of the gravel.
    assert np.mean([np.mean(patch > 200) for patch in patches]) > 5 * np.mean(texture > 200)
    with pytest.raises(ValueError, match="fit in the"):
        road_patch(np.random.default_rng(0), (600, 10))


def test_intensity_change_is_undone_by_matching():
    truth = lidar_truth((16, 16), 4.0, 8.0)
    local, prior, valid = stack(SyntheticPairs(truth, 300, seed=4, gain_std=0.2, offset_std=20.0), 300)
    raw, defined = empirical_variance(local, prior, valid)
    matched, _ = empirical_variance(local, match_intensity(local, prior, valid), valid)
    raw_error = float((raw[defined] / truth.variance[defined] - 1).abs().mean())
    matched_error = float((matched[defined] / truth.variance[defined] - 1).abs().mean())
    assert matched_error < 0.1 < 1.0 < raw_error


@pytest.mark.parametrize(
    ("make", "error", "match"),
    [
        (lambda: SyntheticPairs("lidar", 4), TypeError, "VarianceTruth"),
        (lambda: SyntheticPairs(lidar_truth((8, 8)), 0), ValueError, "count"),
        (lambda: SyntheticPairs(lidar_truth((8, 8)), 4, seed=-1), ValueError, "seed"),
        (lambda: SyntheticPairs(lidar_truth((8, 8)), 4, gain_std=-0.1), ValueError, "gain_std"),
        (lambda: SyntheticPairs(lidar_truth((8, 8)), 4, offset_std=float("nan")), ValueError, "offset_std"),
        (lambda: SyntheticPairs(lidar_truth((600, 8)), 4), ValueError, r"at most \(512, 512\)"),
    ],
)
def test_invalid_inputs(make, error, match):
    with pytest.raises(error, match=match):
        make()
