"""ECR's shrunk response (the default): its LLR against a dense marginal likelihood, its limits, surfaces, gradients."""

from __future__ import annotations

import math

import pytest
import torch

from enmi_torch import ECR, register
from enmi_torch.functional import ecr, ecr_from_bin_sums, ecr_surface
from enmi_torch.registration import warp_reference
from enmi_torch.scores.base import direct_surface
from enmi_torch.scores.ecr_statistics import bin_sums
from enmi_torch.scores.shrunk_response import bin_positions, response_variance_grid, shrunk_llr, shrunk_llr_terms


def _dense_llr(weight, weighted_value, positions, response_variance) -> float:
    """The log-likelihood ratio by dense generalised least squares on the bin means (float64, a direct loop)."""
    weight, weighted_value, positions = (part.double() for part in (weight, weighted_value, positions))
    occupied = weight > 0
    means = weighted_value[occupied] / weight[occupied]
    variances = 1 / weight[occupied]
    design = torch.stack([torch.ones_like(means), positions[occupied]], 1)

    def log_likelihood(var, columns):
        precision = torch.diag(1 / var)
        x = design[:, :columns]
        beta = torch.linalg.solve(x.T @ precision @ x, x.T @ precision @ means)
        residual = means - x @ beta
        return -0.5 * (torch.log(2 * math.pi * var).sum() + (residual.square() / var).sum()), beta

    shrunk, beta = log_likelihood(variances + response_variance, 2)
    if beta[1] <= 0:  # an increasing line only: a falling trend is flat
        shrunk, _ = log_likelihood(variances + response_variance, 1)
    null, _ = log_likelihood(variances, 1)
    return float(shrunk - null)


@pytest.mark.parametrize("response_variance", [0.0, 0.05, 1.0, 30.0, 4000.0])
@pytest.mark.parametrize("trend", [1.0, -1.0], ids=["rising", "falling"])
def test_llr_equals_the_dense_marginal_likelihood(response_variance, trend, dtype):
    generator = torch.Generator().manual_seed(3)
    bins = 7
    weight = torch.rand(bins, generator=generator, dtype=torch.float64) * 4 + 0.2
    weight[2] = 0.0  # an empty bin is left out
    means = trend * 3 * torch.arange(bins, dtype=torch.float64) + 2 * torch.randn(bins, generator=generator).double()
    weighted_value = weight * (means - 5.0)
    positions = bin_positions(bins, torch.float64)
    result = shrunk_llr_terms(weight.to(dtype), weighted_value.to(dtype), positions.to(dtype), response_variance)
    expected = _dense_llr(weight, weighted_value, positions, response_variance)
    tolerance = 1e-9 if dtype == torch.float64 else 2e-4
    assert result.dtype == dtype
    assert abs(float(result) - expected) <= tolerance * max(1.0, abs(expected))


def test_llr_is_batched_over_trailing_dimensions():
    generator = torch.Generator().manual_seed(4)
    weight = torch.rand(5, 3, 2, generator=generator, dtype=torch.float64) + 0.5
    weighted_value = torch.randn(5, 3, 2, generator=generator, dtype=torch.float64) * 4
    positions = bin_positions(5, torch.float64)
    whole = shrunk_llr_terms(weight, weighted_value, positions[:, None, None], 2.5)
    for row in range(3):
        for col in range(2):
            single = shrunk_llr_terms(weight[:, row, col], weighted_value[:, row, col], positions, 2.5)
            torch.testing.assert_close(whole[row, col], single, rtol=1e-12, atol=1e-12)


def test_the_profile_is_the_maximum_over_delta():
    generator = torch.Generator().manual_seed(5)
    weight = torch.rand(8, 40, generator=generator, dtype=torch.float64) * 3 + 0.1
    curve = (torch.arange(8, dtype=torch.float64) - 3.5).square()[:, None] * torch.rand(40, generator=generator)
    weighted_value = weight * (curve + torch.randn(8, 40, generator=generator, dtype=torch.float64) / weight.sqrt())
    positions = bin_positions(8, torch.float64)[:, None]
    llr, chosen = shrunk_llr(weight, weighted_value, positions, (0.0, 8.0))
    fine = torch.stack(
        [shrunk_llr_terms(weight, weighted_value, positions, 64 * 10 ** (k / 40)) for k in range(-320, 41)]
        + [shrunk_llr_terms(weight, weighted_value, positions, 0.0)]
    ).amax(0)
    grid = torch.stack([shrunk_llr_terms(weight, weighted_value, positions, v) for v in response_variance_grid((0, 8))])
    assert bool((llr >= grid.amax(0) - 1e-12).all())  # the parabola's vertex is never below the best grid point
    assert float((fine - llr).abs().max()) < 0.05  # within a twentieth of a nat of the fine maximum
    at_chosen = torch.stack(
        [shrunk_llr_terms(weight[:, m], weighted_value[:, m], positions[:, 0], float(chosen[m])) for m in range(40)]
    )
    assert float((fine - at_chosen).max()) < 0.05  # and the delta^2 it reports is where the maximum lies
    assert bool((chosen[curve[0] > 3] > 0).all())  # a curved response leaves the line


def _linear_pair(dtype, generator):
    """A map on bin centres (8 bins over 0..256) and a captured image on an increasing line of it, plus noise."""
    centres = 16.0 + 32.0 * torch.randint(0, 8, (3, 1, 12, 20), generator=generator)
    noise = torch.randn(3, 1, 12, 20, generator=generator)
    variance = 20 + 300 * torch.rand(1, 1, 12, 20, generator=generator)
    captured = 40 + 0.6 * centres + variance.sqrt() * noise
    return captured.to(dtype), centres.to(dtype), variance.to(dtype)


def test_a_linear_pair_scores_as_the_linear_response(dtype, tolerance):
    generator = torch.Generator().manual_seed(6)
    captured, reference, variance = _linear_pair(dtype, generator)
    noiseless = (40 + 0.6 * reference).to(dtype)
    options = {"bins": 8, "model_variance": 9.0}
    shrunk = ecr(noiseless, reference, variance, **options)
    linear = ecr(noiseless, reference, variance, response="linear", **options)
    torch.testing.assert_close(shrunk, linear, **tolerance)
    # With noise the line is still what the data support: far nearer the linear score than the binned one.
    shrunk, linear, binned = (ecr(captured, reference, variance, response=r, **options) for r in ECR_RESPONSES)
    assert bool(((shrunk - linear).abs() < 0.25 * (binned - linear).abs()).all())


ECR_RESPONSES = ("shrunk", "linear", "binned")


def test_a_non_monotonic_pair_keeps_the_binned_response(generator):
    reference = torch.rand(2, 1, 40, 48, generator=generator, dtype=torch.float64) * 256
    vee = 255 * (2 * reference / 255 - 1).abs() ** 0.8
    captured = vee + 8 * torch.randn(reference.shape, generator=generator, dtype=torch.float64)
    shrunk, linear, binned = (ecr(captured, reference, 64.0, response=r) for r in ECR_RESPONSES)
    assert bool((linear.abs() < 0.01).all())  # the line finds nothing
    assert bool((shrunk > 0.95 * binned).all())  # the shrunk response keeps what the bins find
    wrong = ecr(captured, reference.roll(1, 0), 64.0)
    assert bool((shrunk > 100 * wrong.abs()).all())


def test_a_falling_response_is_not_a_line():
    # An inverted image fits only a falling line: the shrunk response takes it through the deviations, not the slope.
    reference = torch.linspace(0, 255, 64, dtype=torch.float64).repeat(4, 1)
    inverted = 255 - reference
    sums = bin_sums(inverted, reference[None], torch.full_like(reference, 4.0), None, 8, (0.0, 256.0))
    positions = bin_positions(8, torch.float64)
    flat = shrunk_llr_terms(sums.weight[0].T, sums.weighted_value[0].T, positions, 0.0)
    torch.testing.assert_close(flat, torch.zeros_like(flat), rtol=0, atol=1e-9)
    rising = ecr(reference[:, None], reference[:, None], 4.0, bins=8, model_variance=0.0)  # flat samples (B, 1, N)
    falling = ecr(inverted[:, None], reference[:, None], 4.0, bins=8, model_variance=0.0)
    assert bool((falling > 0).all()) and bool((falling < rising).all())  # the Occam factor of leaving the line


def test_bin_sums_stream_into_the_shrunk_score(dtype, tolerance):
    generator = torch.Generator().manual_seed(7)
    captured, reference, variance = _linear_pair(dtype, generator)
    flat = captured.flatten(1), reference.flatten(1)[None], variance.flatten(1).expand(3, -1) + 9.0
    whole = bin_sums(*flat, None, 8, (0.0, 256.0), centre=50.0)
    halves = [
        bin_sums(flat[0][:, part], flat[1][..., part], flat[2][:, part], None, 8, (0.0, 256.0), centre=50.0)
        for part in (slice(0, 100), slice(100, None))
    ]
    summed = type(whole)(*(first + second for first, second in zip(*halves, strict=True)))
    torch.testing.assert_close(ecr_from_bin_sums(summed), ecr_from_bin_sums(whole), **tolerance)
    expected = ecr(captured, reference, variance, bins=8, model_variance=9.0)
    torch.testing.assert_close(ecr_from_bin_sums(whole)[0], expected, **tolerance)
    with pytest.raises(ValueError, match="response must be one of"):
        ecr_from_bin_sums(whole, response="linear")


def test_the_surface_equals_the_direct_loop(dtype):
    generator = torch.Generator().manual_seed(8)
    window = torch.rand(1, 1, 22, 27, generator=generator, dtype=torch.float64) * 256
    captured = 30 + 0.7 * window[..., 5:15, 3:19] + 6 * torch.randn(2, 1, 10, 16, generator=generator).double()
    variance = 10 + 60 * torch.rand(2, 1, 10, 16, generator=generator, dtype=torch.float64)
    reference_mask = torch.ones(1, 1, 22, 27, dtype=torch.bool)
    reference_mask[..., 0, :4] = False  # masked cells change which bins each placement holds
    score = ECR(bins=12)
    fast = score.surface(captured.to(dtype), window.to(dtype), variance.to(dtype), reference_mask=reference_mask)
    slow = direct_surface(score, captured, window, variance, reference_mask=reference_mask)
    tolerance = {"rtol": 1e-7, "atol": 1e-9} if dtype == torch.float64 else {"rtol": 2e-3, "atol": 2e-4}
    torch.testing.assert_close(fast.score.double(), slow.score, **tolerance)
    assert divmod(int(fast.score[0].flatten().argmax()), fast.score.shape[-1]) == (5, 3)


def test_the_shrunk_score_is_differentiable():
    generator = torch.Generator().manual_seed(9)
    reference = torch.rand(2, 1, 6, 7, generator=generator, dtype=torch.float64) * 256
    captured = (20 + 0.5 * reference + 20 * torch.randn(2, 1, 6, 7, generator=generator).double()).requires_grad_()
    variance = (50 + 100 * torch.rand(1, 1, 6, 7, generator=generator, dtype=torch.float64)).requires_grad_()
    for response_variance in (0.0, 30.0):
        assert torch.autograd.gradcheck(
            lambda c, v, d=response_variance: ecr(c, reference, v, bins=6, model_variance=30.0, response_variance=d),
            (captured, variance),
            eps=1e-6,
            atol=1e-6,
        )
    # An estimated delta^2 is held fixed, as an estimated tau^2: value and gradient are those of the fixed one.
    score = ECR(bins=6, model_variance=30.0)
    delta2 = score.response_variance_of(captured, reference, variance)
    assert delta2.shape == (2,) and bool((delta2 > 0).any())  # the fixture leaves the line somewhere
    for sample in range(2):
        pair = (captured[sample : sample + 1], reference[sample : sample + 1], variance)
        estimated = score(*pair)
        fixed = score.replace(response_variance=float(delta2[sample]))(*pair)
        torch.testing.assert_close(estimated, fixed, rtol=1e-12, atol=1e-12)
        gradients = [torch.autograd.grad(value.sum(), pair[:1] + pair[2:]) for value in (estimated, fixed)]
        for first, second in zip(*gradients, strict=True):
            torch.testing.assert_close(first, second, rtol=1e-12, atol=1e-12)


def test_the_default_beats_the_binned_response_on_a_noisy_linear_search(generator):
    # Many noisy pixels per bin and a linear response: the free bin means fit the noise, the shrunk ones do not.
    window = torch.rand(1, 1, 1, 48, 48, generator=generator)[0] * 256
    window = torch.nn.functional.avg_pool2d(window, 5, 1, 2)  # a smooth map, as photographs are
    found = {"shrunk": 0, "binned": 0}
    for trial in range(12):
        row, col = divmod(trial * 7 % 121, 11)
        captured = window[..., row : row + 38, col : col + 38] + 110 * torch.randn(1, 1, 38, 38, generator=generator)
        for response in found:
            score = ecr_surface(captured, window, 110.0**2, response=response).score[0]
            found[response] += divmod(int(score.flatten().argmax()), 11) == (row, col)
    assert found["shrunk"] > found["binned"]


def test_registration_with_the_shrunk_response():
    generator = torch.Generator().manual_seed(10)
    reference = torch.rand(1, 1, 50, 50, generator=generator, dtype=torch.float64) * 255
    reference = torch.nn.functional.avg_pool2d(reference, 3, 1, 1)
    truth = torch.tensor([[25.3, 24.6, 2.0]], dtype=torch.float64)
    captured = warp_reference(reference, truth, (20, 22))[0]
    vee = 255 * (2 * captured / 255 - 1).abs() ** 0.8  # a non-monotonic sensor: the line cannot register it
    start = truth + torch.tensor([[0.5, -0.4, 1.0]], dtype=torch.float64)
    for image in (captured, vee):
        noisy = image + 2 * torch.randn(image.shape, generator=generator, dtype=torch.float64)
        found = register(noisy, reference, 4.0, pose=start, score=ECR())
        assert float((found.pose - truth)[0, :2].abs().max()) < 0.1


def test_bin_positions_are_centred_bin_indices():
    torch.testing.assert_close(bin_positions(5, torch.float64), torch.tensor([-2.0, -1.0, 0.0, 1.0, 2.0]).double())


def test_one_occupied_bin_has_no_slope_in_float32():
    # One bin far from the middle: the spread of the positions is zero up to round-off, and no slope is fitted.
    weight = torch.zeros(32)
    weighted_value = torch.zeros(32)
    weight[31], weighted_value[31] = 3.7e3, 1.9e4
    llr = torch.stack([shrunk_llr_terms(weight, weighted_value, bin_positions(32, torch.float32), v) for v in (0, 5.0)])
    # Within the round-off of the terms that cancel (S^2 / W ~ 1e5 in float32).
    torch.testing.assert_close(llr, torch.tensor([0.0, -0.5 * math.log1p(5.0 * 3.7e3)]), rtol=0, atol=0.05)


def test_a_deviation_beyond_the_grid_takes_its_last_point():
    # Bin means a hundred times the value range apart: the profile still rises at the grid's end, taken as it is.
    weight = torch.full((4, 1), 50.0, dtype=torch.float64)
    weighted_value = 50.0 * torch.tensor([[300.0], [-300.0], [-300.0], [300.0]], dtype=torch.float64)
    positions = bin_positions(4, torch.float64)
    llr, chosen = shrunk_llr(weight, weighted_value, positions, (0.0, 1.0))
    grid = response_variance_grid((0.0, 1.0))
    assert float(chosen[0]) == grid[-1]
    torch.testing.assert_close(llr, shrunk_llr_terms(weight, weighted_value, positions, grid[-1]))
