import math

import numpy as np
import pytest
import torch

from enmi_torch import ECR, ECRLoss, localize
from enmi_torch.functional import ecr, ecr_from_bin_sums, ecr_surface
from enmi_torch.scores.ecr import BinSums, ecr_surface_model_variance
from enmi_torch.scores.ecr_model_variance import default_model_variance
from enmi_torch.variance import ConstantVariance


def _numpy_ecr(captured, reference, variance, bins, value_range, model_variance, valid):
    """Independent reference: a loop over the reference bins, weighted group means, in numpy float64."""
    captured, reference = np.asarray(captured, np.float64), np.asarray(reference, np.float64)
    weight = 1.0 / (np.asarray(variance, np.float64) + model_variance)
    width = (value_range[1] - value_range[0]) / bins
    index = np.clip(np.floor((reference - value_range[0]) / width), 0, bins - 1).astype(int)
    keep = np.asarray(valid, bool)
    values, weights, index = captured[keep], weight[keep], index[keep]
    grand_mean = np.sum(weights * values) / np.sum(weights)
    between, occupied = 0.0, 0
    for label in range(bins):
        chosen = index == label
        if not chosen.any():
            continue
        occupied += 1
        group_mean = np.sum(weights[chosen] * values[chosen]) / np.sum(weights[chosen])
        between += np.sum(weights[chosen]) * (group_mean - grand_mean) ** 2
    return (0.5 * between - 0.5 * (occupied - 1)) / keep.sum()


def _case(dtype, shape=(2, 1, 7, 5), seed=0):
    generator = torch.Generator().manual_seed(seed)
    reference = torch.rand(shape, generator=generator, dtype=torch.float64) * 256
    # Non-monotonic response, noise of per-pixel variance, values beyond the range kept as they are.
    captured = 300 * (reference / 256 - 0.4).abs() + torch.randn(shape, generator=generator, dtype=torch.float64) * 20
    variance = torch.rand(shape, generator=generator, dtype=torch.float64) * 400 + 1
    valid = torch.rand(shape, generator=generator) > 0.2
    return captured.to(dtype), reference.to(dtype), variance.to(dtype), valid


@pytest.mark.parametrize("model_variance", [0.0, None, 37.5])
def test_ecr_equals_numpy_group_means(dtype, tolerance, model_variance):
    captured, reference, variance, valid = _case(dtype)
    bins, value_range = 6, (0.0, 256.0)
    options = {"bins": bins, "model_variance": model_variance, "valid_mask": valid, "response": "binned"}
    result = ecr(captured, reference, variance, **options)
    tau2 = default_model_variance(bins, value_range) if model_variance is None else model_variance
    expected = [
        _numpy_ecr(captured[b, 0], reference[b, 0], variance[b, 0], bins, value_range, tau2, valid[b, 0])
        for b in range(captured.shape[0])
    ]
    assert result.dtype == dtype
    torch.testing.assert_close(result, torch.tensor(expected, dtype=dtype), **tolerance)


def test_ecr_candidates_equal_one_call_each_and_roles_are_not_symmetric(dtype, tolerance):
    captured, reference, variance, valid = _case(dtype)
    candidates = torch.stack([reference, reference.flip(-1), captured])
    together = ecr(captured, candidates, variance, bins=5, valid_mask=valid)
    assert together.shape == (3, 2)
    for index in range(3):
        alone = ecr(captured, candidates[index], variance, bins=5, valid_mask=valid)
        torch.testing.assert_close(together[index], alone, **tolerance)
    # The captured image is modelled given the reference bins: swapping the roles changes the score.
    swapped = ecr(reference, captured, variance, bins=5, valid_mask=valid)
    assert not torch.allclose(swapped, together[0], rtol=1e-2)


def test_ecr_with_one_variance_is_the_classic_correlation_ratio():
    captured, reference, _, _ = _case(torch.float64, shape=(1, 1, 9, 11))
    bins, sigma2, tau2 = 7, 90.0, 10.0
    index = np.clip(np.floor(reference.numpy().ravel() / (256 / bins)), 0, bins - 1)
    values = captured.numpy().ravel()
    groups = [values[index == label] for label in range(bins) if (index == label).any()]
    eta2 = sum(len(g) * (g.mean() - values.mean()) ** 2 for g in groups) / np.sum((values - values.mean()) ** 2)
    expected = eta2 * values.var() / (2 * (sigma2 + tau2)) - (len(groups) - 1) / (2 * values.size)
    result = ecr(captured, reference, sigma2, bins=bins, model_variance=tau2, response="binned")
    assert math.isclose(result.item(), expected, rel_tol=1e-10)


def test_ecr_is_centred_under_independence_with_any_variances():
    # 2 LLR is chi^2 with K_occ - 1 degrees of freedom for captured values independent of the reference.
    generator = torch.Generator().manual_seed(3)
    samples, pixels, bins = 400, 300, 8
    variance = torch.rand(samples, pixels, generator=generator, dtype=torch.float64) ** 4 * 1e4 + 0.5
    captured = 100 + torch.randn(samples, pixels, generator=generator, dtype=torch.float64) * variance.sqrt()
    reference = torch.rand(samples, pixels, generator=generator, dtype=torch.float64) * 256
    captured, reference = captured[:, None], reference[:, None]  # flat samples (B, 1, N)
    centred_llr = ecr(captured, reference, variance, bins=bins, model_variance=0.0, response="binned") * pixels
    standard_error = math.sqrt((bins - 1) / 2) / math.sqrt(samples)
    assert abs(centred_llr.mean().item()) < 4 * standard_error
    # Under-stated variances break it: the statistic is no longer centred.
    wrong = ecr(captured, reference, variance / 4, bins=bins, model_variance=0.0, response="binned") * pixels
    assert abs(wrong.mean().item()) > 10 * standard_error


@pytest.mark.parametrize("response", [{"response": "binned"}, {"response_variance": 20.0}], ids=["binned", "shrunk"])
def test_a_pixel_with_a_flat_likelihood_adds_no_evidence(response):
    captured, reference, variance, _ = _case(torch.float64, shape=(1, 1, 6, 6))
    base = ecr(captured, reference, variance, bins=4, model_variance=0.0, **response) * 36
    # One more pixel, in a bin already occupied, with an enormous noise variance and a wild value.
    grown_captured = torch.cat([captured.flatten(1), torch.tensor([[1e4]], dtype=torch.float64)], 1)
    grown_reference = torch.cat([reference.flatten(1), reference.flatten(1)[:, :1]], 1)
    grown_variance = torch.cat([variance.flatten(1), torch.tensor([[1e16]], dtype=torch.float64)], 1)
    grown_captured, grown_reference = grown_captured[:, None], grown_reference[:, None]  # flat samples (B, 1, N)
    grown = ecr(grown_captured, grown_reference, grown_variance, bins=4, model_variance=0.0, **response) * 37
    assert abs((grown - base).item()) < 1e-6
    # The paper's ENMI gives such a pixel a full unit of histogram weight instead.


def test_ecr_masked_equals_cropped_and_masked_pixels_may_hold_nan(dtype, tolerance):
    captured, reference, variance, _ = _case(dtype, shape=(1, 1, 6, 8))
    mask = torch.zeros(1, 1, 6, 8, dtype=torch.bool)
    mask[..., 1:5, 2:7] = True
    poisoned = torch.where(mask, captured, torch.nan)
    masked = ecr(poisoned, reference, variance, bins=5, valid_mask=mask)
    cropped = ecr(captured[..., 1:5, 2:7], reference[..., 1:5, 2:7], variance[..., 1:5, 2:7], bins=5)
    torch.testing.assert_close(masked, cropped, **tolerance)


def test_ecr_gradcheck_in_captured_and_variance():
    captured, reference, variance, valid = _case(torch.float64, shape=(2, 1, 4, 3))
    captured.requires_grad_()
    variance.requires_grad_()

    def score(captured, variance):
        # Fixed variances: estimated ones are held fixed in the gradient (tests/scores/test_ecr_model_variance).
        return ecr(captured, reference, variance, bins=4, valid_mask=valid, model_variance=7.5, response_variance=20.0)

    assert torch.autograd.gradcheck(score, (captured, variance))


def test_ecr_from_bin_sums_streams():
    captured, reference, variance, _ = _case(torch.float64, shape=(1, 1, 8, 8))
    from enmi_torch.scores.ecr_statistics import bin_sums

    # Sums over two halves add up to the sums of the whole: the score can be accumulated across batches.
    tau2 = 5.0
    flat = captured.flatten(1), reference.flatten(1)[None], variance.flatten(1) + tau2
    whole = bin_sums(*flat, None, 4, (0.0, 256.0))
    halves = [
        bin_sums(flat[0][:, part], flat[1][..., part], flat[2][:, part], None, 4, (0.0, 256.0), centre=100.0)
        for part in (slice(0, 30), slice(30, 64))
    ]
    summed = BinSums(*(first + second for first, second in zip(*halves, strict=True)))
    torch.testing.assert_close(ecr_from_bin_sums(summed), ecr_from_bin_sums(whole), rtol=1e-12, atol=1e-12)
    # The sums' own estimate of delta^2, as ecr's on the flat samples.
    flat_samples = captured.flatten(1)[:, None], reference.flatten(1)[None, :, None]  # (B, 1, N), (1, B, 1, N)
    torch.testing.assert_close(
        ecr_from_bin_sums(whole), ecr(*flat_samples, flat[2] - tau2, bins=4, model_variance=tau2)
    )


def test_ecr_loss_agrees_with_function_and_its_variance_model():
    captured, reference, variance, valid = _case(torch.float32)
    loss = ECRLoss(bins=5, reduction="none")
    torch.testing.assert_close(
        loss(captured, reference, variance=variance, valid_mask=valid),
        -ecr(captured, reference, variance, bins=5, valid_mask=valid),
    )
    with_model = ECRLoss(bins=5, variance_model=ConstantVariance(100.0), reduction="sum")
    torch.testing.assert_close(with_model(captured, reference), loss(captured, reference, variance=100.0).sum())
    variance.requires_grad_()
    loss(captured, reference, variance=variance, valid_mask=valid).sum().backward()
    assert torch.isfinite(variance.grad).all() and variance.grad[valid].abs().sum() > 0
    assert (variance.grad[~valid] == 0).all()
    with pytest.raises(ValueError, match="variance must be None when ECRLoss has a variance_model"):
        with_model(captured, reference, variance=1.0)
    linear = ECRLoss(bins=5, reduction="none", response="linear")
    torch.testing.assert_close(
        linear(captured, reference, variance=variance.detach(), valid_mask=valid),
        -ecr(captured, reference, variance.detach(), bins=5, valid_mask=valid, response="linear"),
    )


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"variance": None}, "variance must be"),
        ({"model_variance": -1.0}, "model_variance must be 'estimate', a number >= 0"),
        ({"model_variance": math.inf}, "model_variance must be finite"),
        ({"model_variance": "auto"}, "model_variance must be 'estimate', a number"),
        ({"variance": -1.0}, "variance"),
        ({"bins": 1}, "bins"),
    ],
)
def test_ecr_refuses_bad_arguments(kwargs, message):
    captured, reference, variance, _ = _case(torch.float64)
    arguments = {"variance": variance, **kwargs}
    variance = arguments.pop("variance")
    with pytest.raises(ValueError, match=message):
        ecr(captured, reference, variance, **arguments)


def _numpy_linear_ecr(captured, reference, variance, model_variance, valid):
    """Independent reference: weighted least squares of v on (1, r) with numpy, half the explained sum of squares."""
    keep = np.asarray(valid, bool).ravel()
    values = np.asarray(captured, np.float64).ravel()[keep]
    design = np.stack([np.ones(keep.sum()), np.asarray(reference, np.float64).ravel()[keep]], 1)
    weight = 1.0 / (np.asarray(variance, np.float64).ravel()[keep] + model_variance)
    root = np.sqrt(weight)
    coefficients, *_ = np.linalg.lstsq(design * root[:, None], values * root, rcond=None)
    fitted = design @ coefficients
    mean = np.sum(weight * values) / np.sum(weight)
    explained = np.sum(weight * (fitted - mean) ** 2)
    llr = 0.5 * explained if coefficients[1] > 0 else 0.0
    return (llr - 0.5) / keep.sum()


def test_linear_response_equals_weighted_least_squares_and_ignores_inverted_contrast(dtype, tolerance):
    _, reference, variance, valid = _case(dtype)
    linear = (
        0.6 * reference + 30 + torch.randn(reference.shape, generator=torch.Generator().manual_seed(9), dtype=dtype) * 9
    )
    result = ecr(linear, reference, variance, model_variance=4.0, valid_mask=valid, response="linear")
    expected = [_numpy_linear_ecr(linear[b, 0], reference[b, 0], variance[b, 0], 4.0, valid[b, 0]) for b in range(2)]
    torch.testing.assert_close(result, torch.tensor(expected, dtype=dtype), **tolerance)
    # An inverted image fits v = a + b r only with b < 0: no evidence for the increasing response.
    inverted = ecr(255 - linear, reference, variance, model_variance=4.0, valid_mask=valid, response="linear")
    torch.testing.assert_close(inverted, torch.full_like(inverted, -0.5) / valid.flatten(1).sum(1).to(dtype))
    # With one variance it is the squared Pearson correlation times the captured spread over the noise variance.
    values, map_values = linear[0].flatten().double(), reference[0].flatten().double()
    correlation = torch.corrcoef(torch.stack([values, map_values]))[0, 1]
    assert correlation > 0
    closed_form = 0.5 * correlation**2 * values.var(unbiased=False) / (50.0 + 4.0) - 0.5 / values.numel()
    uniform = ecr(linear[:1], reference[:1], 50.0, model_variance=4.0, response="linear")
    assert uniform.item() == pytest.approx(closed_form.item(), rel=1e-4)
    with pytest.raises(ValueError, match="response must be one of"):
        ecr(linear, reference, variance, response="cubic")


def test_default_model_variance_is_the_bin_quantisation_variance():
    assert default_model_variance(32, (0.0, 256.0)) == pytest.approx(64 / 12)
    assert default_model_variance(16, (-8.0, 8.0)) == pytest.approx(1 / 12)


def test_a_map_that_falls_in_one_bin_is_refused_where_ecr_bins_it():
    generator = torch.Generator().manual_seed(0)
    reference = torch.rand(1, 1, 24, 24, generator=generator)  # [0, 1] against the default (0, 256)
    captured = reference[..., 4:20, 4:20] + 0.01 * torch.randn(1, 1, 16, 16, generator=generator)
    for surface in (
        lambda: ecr_surface(captured, reference, 1e-4),
        lambda: ECR().surface(captured, reference, 1e-4),
        lambda: ecr_surface_model_variance(captured, reference, 1e-4),  # the tau^2 of that surface: checked alike
    ):
        with pytest.raises(ValueError, match=r"reference varies .* one of the 32 bins of value_range=\(0\.0, 256\.0\)"):
            surface()
    with pytest.raises(ValueError, match="reference varies"):  # the two-stage search bins the map too
        localize(captured, reference, 1e-4, shifts=4, yaws=[-1.0, 0.0, 1.0], search="two_stage")
    fixed = ecr_surface(captured, reference, 1e-4, value_range=(0.0, 1.0))
    assert int(fixed.score[0].argmax()) == 4 * 9 + 4  # the true placement, (4, 4) of 9 x 9
    ecr_surface(captured, reference, 1e-4, response="linear")  # the linear response bins nothing


@pytest.mark.parametrize(
    ("scale", "variance", "model_variance"),
    [(1.0, 1e-30, 0.0), (1.0, 1e-30, "estimate"), (1e20, 1e-30, "estimate"), (1e20, 1e-30, None), (1e18, 1e-4, 0.0)],
)
def test_float32_ecr_and_its_gradient_stay_finite_for_tiny_variances_and_huge_values(scale, variance, model_variance):
    generator = torch.Generator().manual_seed(0)
    reference = torch.rand(2, 1, 8, 8, generator=generator) * 256
    captured = reference + torch.randn(2, 1, 8, 8, generator=generator)
    reference, captured = reference * scale, (captured * scale).requires_grad_()
    noise = torch.full_like(reference, variance * scale**2)
    options = {"value_range": (0.0, 256 * scale), "model_variance": model_variance}
    score = ecr(captured, reference, noise, **options)
    score.sum().backward()
    assert torch.isfinite(score).all() and torch.isfinite(captured.grad).all()
    as_float64 = ecr(captured.detach().double(), reference.double(), noise.double(), **options)
    torch.testing.assert_close(score, as_float64.float(), rtol=1e-4, atol=0.0)


def test_ecr_that_overflows_the_output_dtype_is_refused_not_inf():
    image = torch.arange(64.0).reshape(1, 1, 8, 8) * 4
    assert ecr(image.half(), image.half(), 1.0, model_variance=0.0).dtype == torch.float16
    with pytest.raises(ValueError, match=r"ecr reaches .*, beyond the largest torch.float16 \(6.55e\+04\)"):
        ecr((image + 1).half(), image.half(), 1e-3, model_variance=0.0)


@pytest.mark.parametrize("misfit", ["independent", "correlated"])
def test_held_fit_holds_the_pairs_own_estimates_and_scores_later_pairs_with_them(dtype, tolerance, misfit):
    # A tracker holds the noise model of one pair (Score.held_fit): tau^2 and delta^2 are that pair's estimates,
    # the held score equals the estimating one there, and scores another pair with the first pair's model.
    captured, reference, variance, valid = _case(dtype, shape=(2, 1, 9, 13))
    first = (captured[:1], reference[:1], variance[:1])
    score = ECR(bins=6, misfit=misfit)
    held = score.held_fit(*first, valid_mask=valid[:1])
    tau2 = score.model_variance_of(*(part.double() for part in first), valid_mask=valid[:1])
    delta2 = score.response_variance_of(*(part.double() for part in first), valid_mask=valid[:1])
    assert held == ECR(bins=6, model_variance=float(tau2[0]), response_variance=float(delta2[0]))
    torch.testing.assert_close(held(*first, valid_mask=valid[:1]), score(*first, valid_mask=valid[:1]), **tolerance)
    second = (captured[1:], reference[1:], variance[1:])
    assert float(score.model_variance_of(*second, valid_mask=valid[1:])[0]) != pytest.approx(float(tau2[0]))
    # The binned response has no delta^2: its held tau^2 scores the second pair as the numpy group means do.
    binned = ECR(bins=6, response="binned", misfit=misfit).held_fit(*first, valid_mask=valid[:1])
    assert binned.response_variance == "estimate" and binned.misfit == "independent"
    expected = _numpy_ecr(*(part[0, 0] for part in second), 6, (0.0, 256.0), binned.model_variance, valid[1, 0])
    expected = torch.tensor([expected], dtype=dtype)
    torch.testing.assert_close(binned(*second, valid_mask=valid[1:]), expected, **tolerance)


def test_held_fit_keeps_what_is_fixed_and_refuses_what_it_cannot_hold():
    captured, reference, variance, _ = _case(torch.float64, shape=(2, 1, 9, 13))
    fixed = ECR(bins=6, model_variance=40.0, response_variance=2.0)
    assert fixed.held_fit(captured[:1], reference[:1], variance[:1]) is fixed
    half = ECR(bins=6, model_variance=40.0).held_fit(captured[:1], reference[:1], variance[:1])
    delta2 = ECR(bins=6, model_variance=40.0).response_variance_of(captured[:1], reference[:1], variance[:1])
    assert half == ECR(bins=6, model_variance=40.0, response_variance=float(delta2[0]))
    with pytest.raises(ValueError, match=r"held_fit needs one aligned pair.*got \(2, 1, 9, 13\)"):
        ECR().held_fit(captured, reference, variance)
    with pytest.raises(ValueError, match=r"misfit='regional'.*noise_model='per_frame'"):
        ECR(misfit="regional").held_fit(captured[:1], reference[:1], variance[:1])
    with pytest.raises(ValueError, match="variance must be given for score 'ecr'"):
        ECR().held_fit(captured[:1], reference[:1], None)
