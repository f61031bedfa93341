"""ECR's regional misfit (``misfit="regional"``): the per-pixel ``tau^2(x)`` against a direct loop, a changed patch
weighed down, an unchanged pair kept near its global ``tau^2``, and the values, surfaces and search that use it."""

import math

import pytest
import torch

from enmi_torch import ECR, localize
from enmi_torch.binning import hard_bin_index
from enmi_torch.functional import ecr
from enmi_torch.scores.base import direct_surface
from enmi_torch.scores.ecr import ecr_model_variance, ecr_surface_model_variance
from enmi_torch.scores.ecr_regional_misfit import regional_model_variance, regional_reach

RANGE = (0.0, 256.0)
PATCH = (slice(8, 24), slice(36, 56))  # rows, columns of the changed patch in a 48 x 64 image


def _direct_map(residual, noise, valid, tau2, floor, weights_at=None):
    """:func:`regional_model_variance` of one image by loops over the pixels and their boxes."""
    height, width = residual.shape
    reach_y, reach_x = regional_reach(height, width)
    around = [[tau2 if weights_at is None else float(weights_at[y, x]) for x in range(width)] for y in range(height)]
    local, sampling = {}, {}
    for y in range(height):
        for x in range(width):
            weights, sums = 0.0, 0.0
            for row in range(max(0, y - reach_y), min(height, y + reach_y + 1)):
                for col in range(max(0, x - reach_x), min(width, x + reach_x + 1)):
                    if valid[row, col]:
                        precision = 1 / (float(noise[row, col]) + around[row][col]) ** 2
                        weights += precision
                        sums += precision * (float(residual[row, col]) ** 2 - float(noise[row, col]))
            local[y, x] = sums / weights if weights > 0 else tau2
            sampling[y, x] = 2 / weights if weights > 0 else math.inf
    judged = [(y, x) for y in range(height) for x in range(width) if valid[y, x] and sampling[y, x] < math.inf]
    spread = max(0.0, sum((local[p] - tau2) ** 2 - sampling[p] for p in judged) / len(judged))
    expected = torch.empty(height, width, dtype=torch.float64)
    for (y, x), value in local.items():
        share = spread / (spread + sampling[y, x]) if sampling[y, x] < math.inf else 0.0
        expected[y, x] = max(floor, tau2 + share * (value - tau2))
    return expected


def test_the_map_is_the_shrunk_local_estimate_of_a_direct_loop(dtype, generator):
    # Non-square with unequal reaches (2 rows, 5 columns): a swapped axis moves the boxes. Masked (NaN under the mask),
    # noise that varies down the rows, a misfit that grows to the right, and weights read at a map of their own.
    height, width = 17, 41
    noise = (1 + torch.linspace(0, 3, height, dtype=torch.float64))[:, None].expand(height, width)
    misfit = torch.linspace(0, 6, width, dtype=torch.float64).expand(height, width)
    residual = (noise + misfit).sqrt() * torch.randn(height, width, generator=generator, dtype=torch.float64)
    valid = torch.rand(height, width, generator=generator) > 0.2
    residual = torch.where(valid, residual, math.nan)
    weights_at = 2 + torch.rand(height, width, generator=generator, dtype=torch.float64)
    tolerance = {"rtol": 1e-9, "atol": 1e-9} if dtype == torch.float64 else {"rtol": 1e-4, "atol": 1e-4}
    for around in (None, weights_at):
        found = regional_model_variance(
            residual[None].to(dtype),
            noise[None].to(dtype),
            valid[None],
            torch.tensor([2.5], dtype=dtype),
            0.25,
            None if around is None else around[None].to(dtype),
        )
        expected = _direct_map(residual, noise, valid, 2.5, 0.25, around)
        assert found.dtype == dtype
        torch.testing.assert_close(found[0].double(), expected, **tolerance)
    assert float(expected[:, -5:].mean()) > float(expected[:, :5].mean()) + 2  # the misfit grows to the right


def _images(generator, *, changed: bool, noise_variance=25.0, tau=4.0, dtype=torch.float64):
    """A map, its section at (5, 9) seen with white noise and a uniform misfit; ``changed``: a patch replaced."""
    height, width = 48, 64
    reference = torch.rand(1, 1, height + 12, width + 16, generator=generator, dtype=torch.float64) * 256
    section = reference[..., 5 : 5 + height, 9 : 9 + width]
    means = 40 + 120 * torch.sin(hard_bin_index(section, 32, RANGE).double() * 0.7)
    spread = math.sqrt(noise_variance + tau**2)
    captured = means + spread * torch.randn(1, 1, height, width, generator=generator, dtype=torch.float64)
    if changed:  # other content with the same low sensor noise: a roof that was not there
        captured[(..., *PATCH)] = torch.rand(1, 1, 16, 20, generator=generator, dtype=torch.float64) * 200
    return captured.to(dtype), reference.to(dtype), section.to(dtype)


def test_a_changed_patch_gets_a_larger_model_variance_and_weighs_less(dtype, generator):
    captured, _, section = _images(generator, changed=True, dtype=dtype)
    tau2 = ecr_model_variance(captured, section, 25.0, misfit="regional")
    assert tau2.shape == (1, 48, 64) and tau2.dtype == torch.float64
    inside = tau2[(0, *PATCH)]
    outside = torch.ones(48, 64, dtype=torch.bool)
    outside[: 24 + 10, 36 - 10 :] = False  # away from the patch by more than a box
    global_tau2 = float(ecr_model_variance(captured, section, 25.0)[0])
    assert float(inside.median()) > 20 * float(tau2[0][outside].median())
    assert float(inside.median()) > global_tau2 > float(tau2[0][outside].median())
    # Unchanged pixels keep about the misfit they show (16 beyond the noise), not the patch's share of the average.
    assert 4 < float(tau2[0][outside].median()) < 40
    weight = 1 / (25.0 + tau2[0])
    assert float(weight[PATCH].median()) < 0.1 * float(weight[outside].median())
    assert float(weight[PATCH].max()) < float(weight[outside].min())  # even the patch's edges, read half outside it


def test_an_unchanged_pair_keeps_a_near_uniform_map_near_its_global_estimate(generator):
    for _ in range(3):
        captured, _, section = _images(generator, changed=False)
        tau2 = ecr_model_variance(captured, section, 25.0, misfit="regional")[0]
        global_tau2 = float(ecr_model_variance(captured, section, 25.0)[0])
        assert float(tau2.std()) < 0.2 * global_tau2
        assert float(tau2.mean()) == pytest.approx(global_tau2, rel=0.1)


def test_ecr_with_a_regional_misfit_is_ecr_with_its_map_added_to_the_noise(dtype, generator):
    captured, _, section = _images(generator, changed=True, dtype=dtype)
    mask = torch.rand(captured.shape, generator=generator) > 0.1
    for response in ("shrunk", "binned", "linear"):
        score = ECR(misfit="regional", response=response)
        tau2 = score.model_variance_of(captured, section, 25.0, valid_mask=mask)
        delta2 = score.response_variance_of(captured, section, 25.0, valid_mask=mask)
        value = score(captured, section, 25.0, valid_mask=mask)
        held = (25.0 + tau2[:, None]).to(dtype)
        fixed = {"model_variance": 0.0, "valid_mask": mask}
        if response == "shrunk":  # the other responses have no delta^2 (refused, ECR_RULES)
            fixed["response_variance"] = float(delta2[0])
        torch.testing.assert_close(value, ecr(captured, section, held, response=response, **fixed))
        assert value.dtype == dtype
    # The patch weighed down, the quiet pixels around it weighed up: the true section scores higher than with one
    # tau^2 inflated by the patch.
    assert float(ecr(captured, section, 25.0, misfit="regional")[0]) > float(ecr(captured, section, 25.0)[0])


def test_candidates_each_get_their_own_map(generator):
    captured, reference, section = _images(generator, changed=True)
    shifted = reference[..., 6 : 6 + 48, 11 : 11 + 64]
    candidates = torch.stack([section, shifted])
    tau2 = ecr_model_variance(captured, candidates, 25.0, misfit="regional")
    assert tau2.shape == (2, 1, 48, 64)
    torch.testing.assert_close(tau2[0], ecr_model_variance(captured, section, 25.0, misfit="regional"))
    values = ecr(captured, candidates, 25.0, misfit="regional")
    torch.testing.assert_close(values[1], ecr(captured, shifted, 25.0, misfit="regional"))
    assert float(values[0, 0]) > float(values[1, 0])


def test_the_gradient_holds_the_map(generator):
    # The estimate is detached: the gradient is that of ECR with the map added to the noise variance.
    captured, _, section = _images(generator, changed=True)
    captured, section = captured[..., :24, :32].contiguous(), section[..., :24, :32].contiguous()
    tau2 = ecr_model_variance(captured, section, 25.0, misfit="regional", bins=8)
    held = 25.0 + tau2[:, None]
    captured = captured.clone().requires_grad_(True)
    for response in ("binned", "linear"):

        def value(image, response=response):
            return ecr(image, section, held, bins=8, model_variance=0.0, response=response)

        assert torch.autograd.gradcheck(value, (captured,))
        regional = ecr(captured, section, 25.0, bins=8, misfit="regional", response=response)
        (gradient,) = torch.autograd.grad(regional.sum(), captured)
        (expected,) = torch.autograd.grad(value(captured).sum(), captured)
        torch.testing.assert_close(gradient, expected)


def test_a_surface_holds_the_map_of_its_peak_and_the_search_agrees(generator):
    captured, reference, section = _images(generator, changed=True)
    variance = torch.full(captured.shape, 25.0, dtype=torch.float64)
    variance[..., 24:, :] = 36.0  # unequal, so the map and the noise must line up pixel by pixel
    score = ECR(misfit="regional")
    tau2 = score.surface_model_variance(captured, reference, variance)
    assert tau2.shape == (1, 48, 64)
    torch.testing.assert_close(tau2, score.model_variance_of(captured, section, variance), rtol=1e-6, atol=1e-6)
    surface = score.surface(captured, reference, variance)
    assert divmod(int(surface.score[0].argmax()), surface.score.shape[-1]) == (5, 9)
    delta2 = score.surface_response_variance(captured, reference, variance)
    held = variance + tau2[:, None]
    fixed = ECR(model_variance=0.0, response_variance=float(delta2[0]))
    torch.testing.assert_close(surface.score, fixed.surface(captured, reference, held).score, rtol=1e-9, atol=1e-9)
    at_truth = fixed(captured, section, held)
    torch.testing.assert_close(surface.score[:, 5, 9], at_truth, rtol=1e-9, atol=1e-9)
    small = (captured[..., :20, :24], reference[..., :26, :30], variance[..., :20, :24])
    torch.testing.assert_close(direct_surface(score, *small).score, score.surface(*small).score, rtol=1e-9, atol=1e-9)
    options = {"score": score, "shifts": (6, 8), "around": (41, 29), "yaws": [0.0]}
    exhaustive = localize(captured, reference, variance, **options).surface
    staged = localize(captured, reference, variance, search="two_stage", **options).surface
    rescored = torch.isfinite(staged)
    assert int(rescored.sum()) > 0
    torch.testing.assert_close(staged[rescored], exhaustive[rescored], rtol=1e-9, atol=1e-9)
    assert ecr_surface_model_variance(captured, reference, variance, misfit="regional").shape == (1, 48, 64)
    linear = ECR(misfit="regional", response="linear")
    held = variance + linear.surface_model_variance(captured, reference, variance)[:, None]
    expected = ECR(model_variance=0.0, response="linear").surface(captured, reference, held).score
    torch.testing.assert_close(linear.surface(captured, reference, variance).score, expected, rtol=1e-9, atol=1e-9)


def test_a_misfit_with_a_fixed_model_variance_and_bad_misfits_are_refused(generator):
    captured, _, section = _images(generator, changed=True)
    moot = r"misfit='regional' has no effect with model_variance=30.0: .* pass model_variance='estimate'"
    with pytest.raises(ValueError, match=moot):
        ecr_model_variance(captured, section, 25.0, misfit="regional", model_variance=30.0)
    with pytest.raises(ValueError, match=moot):
        ecr(captured, section, 25.0, misfit="regional", model_variance=30.0)
    with pytest.raises(ValueError, match=r"misfit must be one of \['independent', 'correlated', 'regional'\]"):
        ECR(misfit="local")
    with pytest.raises(ValueError, match="misfit must be one of"):
        ecr(captured, section, 25.0, misfit="Regional")
    flat = torch.rand(2, 16, generator=torch.Generator().manual_seed(0)) * 256
    with pytest.raises(ValueError, match=r"captured must have shape \(B, 1, H, W\) or \(B, H, W\), got the 2-D"):
        ecr(flat, flat, 1.0, misfit="regional")
