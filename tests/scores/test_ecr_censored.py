"""ECR with saturated readings censored: against direct maximisation and integration of the censored likelihood."""

import math

import numpy as np
import pytest
import torch
from scipy import integrate, optimize, stats

from enmi_torch import ECR
from enmi_torch.scores.ecr import ecr, ecr_model_variance

BINS, RANGE, CLIP = 8, (0.0, 256.0), (0.0, 255.999)


def _pair(generator, shape=(20, 24), dtype=torch.float64, slope=0.9, offset=40.0):
    """A map section, a per-pixel noise variance (unequal), and a reading clipped at both ends of the range."""
    reference = torch.rand(1, 1, *shape, generator=generator, dtype=dtype) * 256
    variance = 100 + 4000 * torch.rand(1, 1, *shape, generator=generator, dtype=dtype)
    noisy = slope * reference + offset + variance.sqrt() * torch.randn(1, 1, *shape, generator=generator, dtype=dtype)
    return reference, variance, noisy, noisy.clamp(*CLIP)


def _log_terms(values, mean, total, side):
    """Each reading's log-likelihood: the Gaussian density, or the tail probability beyond a saturated reading."""
    scale = np.sqrt(total)
    density = stats.norm.logpdf(values, mean, scale)
    above = stats.norm.logsf(values, mean, scale)
    below = stats.norm.logcdf(values, mean, scale)
    return np.where(side > 0, above, np.where(side < 0, below, density))


def _sides(values):
    return np.where(values >= CLIP[1], 1.0, np.where(values <= CLIP[0], -1.0, 0.0))


def _flat(*tensors):
    return [tensor.flatten().numpy() for tensor in tensors]


def test_the_binned_response_is_the_maximised_censored_likelihood_ratio(generator):
    reference, variance, _, clipped = _pair(generator)
    tau2 = 30.0
    values, reference_values, noise = _flat(clipped, reference, variance)
    total, side = noise + tau2, _sides(values)
    cells = np.minimum((reference_values / 32).astype(int), BINS - 1)

    def best(members):  # one mean maximising the censored log-likelihood of these readings
        result = optimize.minimize_scalar(
            lambda mean: -_log_terms(values[members], mean, total[members], side[members]).sum(),
            bounds=(-500, 800),
            method="bounded",
            options={"xatol": 1e-10},
        )
        return -result.fun

    model = sum(best(cells == cell) for cell in np.unique(cells))
    null = best(np.ones_like(cells, dtype=bool))
    expected = (model - null - (len(np.unique(cells)) - 1) / 2) / values.size
    score = ecr(clipped, reference, variance, bins=BINS, model_variance=tau2, response="binned")
    assert float(score) == pytest.approx(expected, rel=1e-8, abs=1e-9)
    assert int((side != 0).sum()) > 30  # the case tells censored from Gaussian readings apart
    gaussian = ecr(clipped, reference, variance, bins=BINS, model_variance=tau2, response="binned", saturation=None)
    assert abs(float(gaussian) - expected) > 1e-3


def test_the_linear_response_is_the_maximised_censored_likelihood_ratio(generator):
    reference, variance, _, clipped = _pair(generator, shape=(16, 21))
    tau2 = 12.0
    values, reference_values, noise = _flat(clipped, reference, variance)
    total, side = noise + tau2, _sides(values)

    def fitted(parameters):
        offset, slope = parameters
        return -_log_terms(values, offset + slope * reference_values, total, side).sum()

    model = -optimize.minimize(fitted, x0=[0.0, 1.0], bounds=[(-500, 500), (0, 5)], method="L-BFGS-B", tol=1e-14).fun
    null = -optimize.minimize_scalar(
        lambda mean: -_log_terms(values, mean, total, side).sum(), bounds=(-500, 800), method="bounded"
    ).fun
    expected = (model - null - 0.5) / values.size
    score = ecr(clipped, reference, variance, bins=BINS, model_variance=tau2, response="linear")
    assert float(score) == pytest.approx(expected, rel=1e-6)


@pytest.mark.slow
def test_the_shrunk_response_is_the_marginal_likelihood_to_the_laplace_approximation():
    """The bin means' deviations from the line integrated out numerically, the line by maximisation.

    Each bin's integral is Laplace's approximation about the fit's mode: here (at most 9 of a bin's 40 readings
    saturated) within a thousandth of a nat. It is not exact: where most of a bin saturates the integrand is skewed
    (24 of 43 saturated readings in one bin: 1.05 nats over the image's 710).
    """
    generator = torch.Generator().manual_seed(0)
    reference, variance, _, clipped = _pair(generator, shape=(16, 20), slope=1.0, offset=30.0)
    tau2, delta2 = 25.0, 40.0
    values, reference_values, noise = _flat(clipped, reference, variance)
    total, side = noise + tau2, _sides(values)
    cells = np.minimum((reference_values / 32).astype(int), BINS - 1)
    positions = np.arange(BINS) - (BINS - 1) / 2
    deviations = np.linspace(-120.0, 120.0, 2401)  # 0.1 grey levels apart; the prior's sd is 6.3
    log_prior = stats.norm.logpdf(deviations, 0.0, math.sqrt(delta2))

    def log_marginal(parameters):
        offset, slope = parameters
        result = 0.0
        for cell in np.unique(cells):
            members = cells == cell
            means = offset + slope * positions[cell] + deviations[:, None]
            log_joint = _log_terms(values[members], means, total[members], side[members]).sum(1) + log_prior
            peak = log_joint.max()
            result += peak + math.log(integrate.trapezoid(np.exp(log_joint - peak), deviations))
        return result

    fit = optimize.minimize(lambda p: -log_marginal(p), x0=[30.0, 30.0], method="L-BFGS-B", options={"ftol": 1e-13})
    null = -optimize.minimize_scalar(
        lambda mean: -_log_terms(values, mean, total, side).sum(), bounds=(-500, 800), method="bounded"
    ).fun
    expected_llr = -fit.fun - null
    score = ecr(clipped, reference, variance, bins=BINS, model_variance=tau2, response_variance=delta2)
    assert int((side != 0).sum()) > 20
    assert float(score) * values.size + 0.5 == pytest.approx(expected_llr, abs=2e-3)


@pytest.mark.parametrize("response", ["shrunk", "binned", "linear"])
def test_readings_that_were_not_clipped_score_as_the_gaussian_model(generator, response):
    reference, variance, noisy, _ = _pair(generator)
    inside = noisy.clamp(1.0, 255.0)  # within the range but at no end of it
    for captured in (noisy, inside):  # noisy reads beyond both ends: no end is a limit of that image
        default = ECR(bins=BINS, response=response)(captured, reference, variance)
        gaussian = ECR(bins=BINS, response=response, saturation=None)(captured, reference, variance)
        assert torch.equal(default, gaussian)
        estimate = ecr_model_variance(captured, reference, variance, bins=BINS, response=response)
        assert torch.equal(estimate, ecr_model_variance(captured, reference, variance, bins=BINS, saturation=None))


@pytest.mark.parametrize("response", ["shrunk", "binned", "linear"])
def test_gradients_with_saturated_readings_match_finite_differences(generator, response):
    """Through the fit's mode (its last Newton step) and each saturated reading's tail, which starts at the reading."""
    reference, variance, _, clipped = _pair(generator, shape=(6, 7))
    inside = (clipped > CLIP[0]) & (clipped < CLIP[1])
    values = clipped.clone().requires_grad_()
    noise = variance.clone().requires_grad_()
    options = {"bins": 4, "model_variance": 40.0, "response": response}
    if response == "shrunk":
        options["response_variance"] = 30.0
    assert 0 < int((~inside).sum()) < inside.numel()
    torch.autograd.gradcheck(lambda v, s: ecr(v, reference, s, **options), (values, noise))


def test_float32_and_float64_agree_with_saturated_readings(generator):
    reference, variance, _, clipped = _pair(generator, shape=(32, 24))
    double = ECR(bins=16)(clipped, reference, variance)
    single = ECR(bins=16)(clipped.float(), reference.float(), variance.float())
    assert single.dtype == torch.float32
    torch.testing.assert_close(single.double(), double, rtol=1e-4, atol=1e-6)


def test_the_censored_estimate_recovers_the_model_variance_that_clipping_hides(generator):
    """Heavy clipping: the Gaussian estimate reads the piles at the ends as quiet pixels; the censored one does not."""
    shape = (1, 1, 96, 96)
    reference = torch.rand(*shape, generator=generator, dtype=torch.float64) * 256
    misfit = 40.0 * torch.randn(*shape, generator=generator, dtype=torch.float64)  # tau^2 = 1600
    noise = 30.0 * torch.randn(*shape, generator=generator, dtype=torch.float64)  # sigma^2 = 900
    captured = (1.6 * reference - 80 + misfit + noise).clamp(*CLIP)
    clipped_share = float(((captured <= 0) | (captured >= CLIP[1])).double().mean())
    assert clipped_share > 0.3
    censored = float(ecr_model_variance(captured, reference, 900.0, bins=32))
    gaussian = float(ecr_model_variance(captured, reference, 900.0, bins=32, saturation=None))
    assert censored == pytest.approx(1600, rel=0.15)
    assert gaussian < 0.6 * 1600
