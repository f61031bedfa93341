import math

import numpy as np
import pytest
import torch
from scipy import integrate, stats

from enmi_torch.binning import (
    bin_centers,
    bin_edges,
    gaussian_log_prior,
    hard_bin_index,
    likelihood_weights,
    likelihood_weights_vjp,
    min_variance,
    parzen_weights,
)

RANGE = (0.0, 256.0)


def test_edges_and_centres_match_numpy():
    np.testing.assert_allclose(bin_edges(32, RANGE, dtype=torch.float64).numpy(), np.linspace(0, 256, 33))
    np.testing.assert_allclose(bin_centers(32, RANGE, dtype=torch.float64).numpy(), np.arange(32) * 8 + 4.0)


def test_hard_index_matches_numpy_digitize_and_clips(generator):
    values = torch.rand(10_000, generator=generator, dtype=torch.float64) * 300 - 20
    edges = np.linspace(0, 256, 33)
    expected = np.clip(np.digitize(values.numpy(), edges) - 1, 0, 31)
    np.testing.assert_array_equal(hard_bin_index(values, 32, RANGE).numpy(), expected)


@pytest.mark.parametrize("kernel", ["hard", "triangular", "xu"])
def test_parzen_rows_are_probabilities(kernel, dtype, generator):
    values = (torch.rand(500, generator=generator, dtype=torch.float64) * 300 - 20).to(dtype)
    weights = parzen_weights(values, 16, RANGE, kernel)
    assert weights.shape == (500, 16)
    assert (weights >= 0).all()
    torch.testing.assert_close(weights.sum(-1), torch.ones(500, dtype=dtype))


def test_triangular_is_linear_interpolation_between_centres():
    weights = parzen_weights(torch.tensor([10.0], dtype=torch.float64), 32, RANGE, "triangular")
    # 10 lies between centres 4 (bin 0) and 12 (bin 1), a quarter of the way from 12.
    torch.testing.assert_close(weights[0, :3], torch.tensor([0.25, 0.75, 0.0], dtype=torch.float64))


def test_mass_weights_equal_scipy_normal_bin_probabilities(dtype, generator, tolerance):
    values = torch.rand(200, generator=generator, dtype=torch.float64) * 256
    variance = torch.rand(200, generator=generator, dtype=torch.float64) * 400 + 0.5
    weights = likelihood_weights(values.to(dtype), variance.to(dtype), 32, RANGE, "mass")
    edges = np.linspace(0, 256, 33)
    cdf = stats.norm.cdf(edges[None, 1:-1], loc=values.numpy()[:, None], scale=np.sqrt(variance.numpy())[:, None])
    expected = np.diff(np.concatenate([np.zeros((200, 1)), cdf, np.ones((200, 1))], axis=1), axis=1)
    atol = 1e-6 if dtype == torch.float32 else 1e-12
    np.testing.assert_allclose(weights.double().numpy(), expected, atol=atol)


def test_mass_weights_equal_numerical_integration_of_the_density():
    value, variance = 97.3, 150.0
    weights = likelihood_weights(
        torch.tensor([value], dtype=torch.float64), torch.tensor([variance]).double(), 8, RANGE
    )
    edges = [value - 40 * math.sqrt(variance), *np.linspace(0, 256, 9)[1:-1], value + 40 * math.sqrt(variance)]
    density = stats.norm(value, math.sqrt(variance)).pdf
    for index in range(8):
        integral, _ = integrate.quad(density, edges[index], edges[index + 1], epsabs=1e-13, limit=200)
        assert abs(integral - weights[0, index].item()) < 1e-9


def test_density_weights_are_normalised_gaussian_at_centres(generator):
    values = torch.rand(50, generator=generator, dtype=torch.float64) * 256
    variance = torch.full((50,), 30.0, dtype=torch.float64)
    weights = likelihood_weights(values, variance, 32, RANGE, "density")
    centres = np.arange(32) * 8 + 4.0
    raw = np.exp(-((centres[None] - values.numpy()[:, None]) ** 2) / 60.0)
    np.testing.assert_allclose(weights.numpy(), raw / raw.sum(1, keepdims=True), rtol=1e-10, atol=1e-300)


@pytest.mark.parametrize("mode", ["mass", "density"])
def test_prior_gives_the_normalised_posterior(mode, generator):
    values = torch.rand(40, generator=generator, dtype=torch.float64) * 256
    variance = torch.full((40,), 200.0, dtype=torch.float64)
    log_prior = gaussian_log_prior(128, 32, 32, RANGE, dtype=torch.float64)
    posterior = likelihood_weights(values, variance, 32, RANGE, mode, log_prior)
    likelihood = likelihood_weights(values, variance, 32, RANGE, mode).numpy() * np.exp(log_prior.numpy())
    np.testing.assert_allclose(posterior.numpy(), likelihood / likelihood.sum(1, keepdims=True), rtol=1e-9, atol=1e-15)


def test_gaussian_log_prior_matches_scipy():
    prior = gaussian_log_prior(128, 32, 32, RANGE, dtype=torch.float64).exp().numpy()
    cdf = stats.norm.cdf(np.linspace(0, 256, 33)[1:-1], 128, 32)
    np.testing.assert_allclose(prior, np.diff(np.concatenate([[0], cdf, [1]])), rtol=1e-9, atol=1e-300)


@pytest.mark.parametrize("mode", ["mass", "density"])
@pytest.mark.parametrize("with_prior", [False, True])
def test_closed_form_vjp_equals_autograd(mode, with_prior, generator):
    values = (torch.rand(64, generator=generator, dtype=torch.float64) * 300 - 20).requires_grad_()
    variance = (torch.rand(64, generator=generator, dtype=torch.float64) * 300 + 1e-3).requires_grad_()
    upstream = torch.randn(64, 16, generator=generator, dtype=torch.float64)
    log_prior = gaussian_log_prior(100, 40, 16, RANGE, dtype=torch.float64) if with_prior else None
    weights = likelihood_weights(values, variance, 16, RANGE, mode, log_prior)
    expected = torch.autograd.grad(weights, (values, variance), upstream)
    actual = likelihood_weights_vjp(values.detach(), variance.detach(), upstream, 16, RANGE, mode, log_prior)
    for got, want in zip(actual, expected, strict=False):
        torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("mode", ["mass", "density"])
def test_tiny_variance_gives_unit_counts_and_finite_gradients(mode, dtype):
    values = torch.tensor([3.0, 100.5, 255.9], dtype=dtype, requires_grad=True)
    variance = torch.full((3,), 1e-30, dtype=dtype, requires_grad=True)
    weights = likelihood_weights(values, variance, 32, RANGE, mode)
    torch.testing.assert_close(weights, parzen_weights(values.detach(), 32, RANGE, "hard"))
    weights.pow(2).sum().backward()
    assert torch.isfinite(values.grad).all() and torch.isfinite(variance.grad).all()
    grads = likelihood_weights_vjp(values.detach(), variance.detach(), torch.ones(3, 32, dtype=dtype), 32, RANGE, mode)
    assert all(torch.isfinite(grad).all() for grad in grads)
    assert min_variance(32, RANGE) == pytest.approx((8e-6) ** 2)


def test_reliability_weights_follow_the_signal_share_of_the_variance():
    from enmi_torch.binning import reliability_weights

    generator = torch.Generator().manual_seed(2)
    values = torch.randn(2, 50, generator=generator, dtype=torch.float64) * 30 + 100
    variance = torch.rand(2, 50, generator=generator, dtype=torch.float64) * 400 + 1
    valid = torch.rand(2, 50, generator=generator) > 0.3
    result = reliability_weights(values, variance, valid)
    for sample in range(2):
        kept = valid[sample]
        signal = max(
            values[sample][kept].var(unbiased=False) - variance[sample][kept].mean(),
            0.01 * values[sample][kept].var(unbiased=False),
        )
        expected = torch.where(kept, signal / (signal + variance[sample]), 0.0)
        torch.testing.assert_close(result[sample], expected)
    # Equal noise gives equal weights; the noisier pixel weighs less.
    equal = reliability_weights(values, torch.full_like(values, 50.0))
    assert torch.allclose(equal, equal[:, :1].expand_as(equal))
    assert result[0, variance[0].argmax()] <= result[0][valid[0]].min() + 1e-12 or not valid[0, variance[0].argmax()]


def test_truncated_weights_put_values_far_outside_the_range_in_the_nearest_edge_bin():
    from enmi_torch.binning import truncated_likelihood_weights

    values = torch.tensor([-1e6, -5e3, 1e6, 5e3], dtype=torch.float64)
    weights = truncated_likelihood_weights(values, torch.full_like(values, 400.0), 8, (0.0, 256.0))
    expected = torch.zeros(4, 8, dtype=torch.float64)
    expected[:2, 0] = 1
    expected[2:, -1] = 1
    torch.testing.assert_close(weights, expected, rtol=0, atol=1e-12)


def test_hard_bins_of_a_range_that_does_not_start_at_zero():
    values = torch.tensor([-3.5, -3.0, -2.01, 0.0, 4.99, 5.0, 12.99, 13.0, 40.0], dtype=torch.float64)
    edges = np.linspace(-3.0, 13.0, 9)[1:-1]  # 8 bins of width 2 over [-3, 13)
    expected = np.digitize(values.numpy(), edges)
    np.testing.assert_array_equal(hard_bin_index(values, 8, (-3.0, 13.0)).numpy(), expected)


def test_truncated_weights_mix_their_near_and_tail_forms_consistently():
    import mpmath

    from enmi_torch.binning import truncated_likelihood_weights

    # A value near the bottom of the range with a standard deviation of one bin: the near bins come from the erf
    # form, the far ones (many standard deviations away) from the log_ndtr form; both must be on one scale.
    values = torch.tensor([3.0, 13.0], dtype=torch.float64)
    variance = torch.full_like(values, 16.0)
    weights = truncated_likelihood_weights(values, variance, 12, (0.0, 48.0))
    mpmath.mp.dps = 60
    for row, value in enumerate(values.tolist()):
        masses = [mpmath.ncdf((4 * (k + 1) - value) / 4) - mpmath.ncdf((4 * k - value) / 4) for k in range(12)]
        total = sum(masses)
        expected = torch.tensor([float(mpmath.log(mass / total)) for mass in masses], dtype=torch.float64)
        torch.testing.assert_close(weights[row].log(), expected, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: bin_edges(0, RANGE), r"bins must be an int >= 2, got 0"),
        (
            lambda: likelihood_weights(torch.tensor([3.0]), torch.tensor([-1.0]), 4, RANGE),
            r"variance must be finite and > 0 .* got 1 value\(s\) outside that \(e.g. -1.0\)",
        ),
        (
            lambda: likelihood_weights(torch.tensor([3.0]), torch.tensor([1.0]), 4, RANGE, kernel="gauss"),
            r"kernel must be one of \['mass', 'density', 'truncated'\], got 'gauss'",
        ),
        (
            lambda: parzen_weights(torch.tensor([float("nan")]), 4, RANGE, "triangular"),
            r"values must be finite .* got 1 NaN/inf value\(s\)",
        ),
        (lambda: gaussian_log_prior(4.0, -1.0, 4, RANGE), r"std must be a finite number > 0, got -1.0"),
        (lambda: gaussian_log_prior(4.0, math.nan, 4, RANGE), r"std must be a finite number > 0, got nan"),
        (lambda: gaussian_log_prior(math.inf, 1.0, 4, RANGE), r"mean must be a finite number, got inf"),
    ],
)
def test_public_binning_functions_refuse_arguments_that_gave_garbage(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_triangular_parzen_weights_on_a_range_that_does_not_start_at_zero():
    # Bin centres -6, -2, 2, 6 of (-8, 8): -5 lies a quarter of a bin above the first centre.
    weights = parzen_weights(torch.tensor([-5.0, 3.0], dtype=torch.float64), 4, (-8.0, 8.0), kernel="triangular")
    expected = torch.tensor([[0.75, 0.25, 0.0, 0.0], [0.0, 0.0, 0.75, 0.25]], dtype=torch.float64)
    torch.testing.assert_close(weights, expected)
