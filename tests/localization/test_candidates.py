"""Rotating the captured image: nearest keeps each pixel and its variance, bilinear propagates the noise."""

import torch
from kornia.geometry.transform import rotate

from enmi_torch.localization.candidates import rotate_captured


def test_nearest_rotation_keeps_each_pixel_and_its_variance():
    generator = torch.Generator().manual_seed(3)
    local = torch.rand(1, 1, 20, 20, generator=generator, dtype=torch.float64) * 256
    variance = torch.rand(1, 1, 20, 20, generator=generator, dtype=torch.float64) * 50 + 1
    valid = torch.ones(1, 1, 20, 20, dtype=torch.bool)
    turned, turned_variance, turned_valid = rotate_captured(local, variance, valid, [0.0, 17.0, -40.0], "nearest")
    assert torch.equal(turned[0], local[0]) and torch.equal(turned_variance[0], variance[0])
    pairs = {(value, noise) for value, noise in zip(local.flatten().tolist(), variance.flatten().tolist(), strict=True)}
    for yaw in (1, 2):
        kept = turned_valid[yaw, 0]
        assert 0.6 * 400 < kept.sum() < 400
        moved = zip(turned[yaw, 0][kept].tolist(), turned_variance[yaw, 0][kept].tolist(), strict=True)
        assert set(moved) <= pairs


def test_bilinear_rotation_propagates_the_noise_variance():
    generator = torch.Generator().manual_seed(4)
    sigma2 = torch.full((1, 1, 16, 16), 9.0, dtype=torch.float64)
    valid = torch.ones(1, 1, 16, 16, dtype=torch.bool)
    _, predicted, kept = rotate_captured(torch.zeros_like(sigma2), sigma2, valid, [23.0], "bilinear")
    noise = 3.0 * torch.randn(4000, 1, 16, 16, generator=generator, dtype=torch.float64)
    empirical = rotate(noise, torch.full((4000,), -23.0, dtype=torch.float64)).var(0)
    ratio = empirical[kept[0]] / predicted[0][kept[0]]
    # 4000 draws: each variance estimate is within about 3 * sqrt(2 / 4000) = 7 % of the truth.
    assert ratio.sub(1).abs().max() < 0.1
    assert predicted[0][kept[0]].min() < 0.6 * 9.0
