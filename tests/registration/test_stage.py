"""A stage of register: both images blurred alike over the pixels that count, the noise carried through the blur."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from enmi_torch import ECR
from enmi_torch.registration import warp_reference
from enmi_torch.registration.stage import Stage


def _case(generator):
    reference = torch.rand(1, 1, 40, 50, generator=generator, dtype=torch.float64) * 255
    pose = torch.tensor([[24.3, 19.6, 12.0]], dtype=torch.float64)
    captured = warp_reference(reference, pose, (11, 14))[0]  # non-square: a swapped axis fails
    variance = 1 + torch.rand(1, 1, 11, 14, generator=generator, dtype=torch.float64) * 30
    mask = torch.ones(1, 1, 11, 14, dtype=torch.bool)
    mask[..., 4, 5] = mask[..., 0, 13] = False
    return reference, pose, captured, variance, mask


def test_the_blur_and_the_noise_it_carries_are_the_normalised_sums_over_the_counted_pixels(generator):
    # Direct loops: each blurred pixel is sum_k g_k c_k / sum_k g_k over the counted pixels k of its 5 x 5 kernel
    # (sigma 0.5), its noise variance sum_k g_k^2 sigma_k^2 / (sum_k g_k)^2. Mutations killed: the noise blurred by
    # g (not g^2), or not normalised by the kernel's mass squared.
    reference, pose, captured, variance, mask = _case(generator)
    stage = Stage(captured, reference, variance, mask, None, ECR(model_variance=2.0), 0.5, 0.0, "bspline")
    fit = stage.setup(pose)
    taps = np.exp(-0.5 * (np.arange(-2, 3) / 0.5) ** 2)
    taps /= taps.sum()
    image, noise, counted = captured[0, 0].numpy(), variance[0, 0].numpy(), mask[0, 0].numpy()
    weights = fit.weights[0].view(11, 14).numpy()
    for row in range(11):
        for col in range(14):
            total = mass = spread = 0.0
            for dy in range(-2, 3):
                for dx in range(-2, 3):
                    if 0 <= row + dy < 11 and 0 <= col + dx < 14 and counted[row + dy, col + dx]:
                        tap = taps[dy + 2] * taps[dx + 2]
                        total, mass = total + tap * image[row + dy, col + dx], mass + tap
                        spread += tap**2 * noise[row + dy, col + dx]
            if not counted[row, col]:
                assert weights[row, col] == 0
                continue
            assert float(stage.values[0, 0, row, col]) == pytest.approx(total / mass, rel=1e-12)
            assert weights[row, col] == pytest.approx(1 / (spread / mass**2 + 2.0), rel=1e-12)


@pytest.mark.parametrize("interpolation", ["bspline", "bilinear"])
def test_the_blurred_comparison_peaks_at_the_truth_at_any_yaw(generator, interpolation):
    # The map's samples are blurred on the captured grid like the captured image: a noiseless image of the map is
    # found where it was cut, turned by 12 degrees, within 5e-4 (a blur of the map before sampling: 5e-3 off).
    from enmi_torch.registration import register

    reference, pose, _, _, _ = _case(generator)
    captured = warp_reference(reference, pose, (11, 14), interpolation=interpolation)[0]
    start = pose + torch.tensor([[0.3, -0.2, 0.5]], dtype=torch.float64)
    found = register(captured, reference, 1.0, pose=start, interpolation=interpolation, tolerance=1e-8)
    assert found.pose[0].tolist() == pytest.approx(pose[0].tolist(), abs=5e-4)
