import itertools
import math

import mpmath
import numpy as np
import pytest
import torch

from enmi_torch import truncated_likelihood_weights
from enmi_torch.binning import _log_bin_masses, likelihood_weights


def test_truncated_weights_equal_trapezoid_integration_of_the_density(dtype, tolerance):
    values = torch.tensor([-20.0, 0.0, 3.7, 100.0, 255.9, 270.0], dtype=torch.float64)
    variance = torch.tensor([400.0, 1.0, 30.0, 2500.0, 9.0, 100.0], dtype=torch.float64)
    bins, value_range = 6, (0.0, 256.0)
    edges = np.linspace(*value_range, bins + 1)
    expected = []
    for value, var in zip(values.tolist(), variance.tolist(), strict=True):
        masses = []
        for low, high in itertools.pairwise(edges):
            grid = np.linspace(low, high, 20001)
            density = np.exp(-((grid - value) ** 2) / (2 * var)) / math.sqrt(2 * math.pi * var)
            masses.append(np.sum((density[1:] + density[:-1]) / 2 * np.diff(grid)))
        expected.append(np.array(masses) / np.sum(masses))
    result = truncated_likelihood_weights(values.to(dtype), variance.to(dtype), bins, value_range)
    assert result.dtype == dtype
    torch.testing.assert_close(result, torch.tensor(np.array(expected), dtype=dtype), rtol=1e-7, atol=tolerance["atol"])


def test_truncated_weights_drop_the_tails_that_mass_weights_fold():
    values, variance = torch.tensor([1.0, 7.5]), torch.tensor([4.0, 1.0])
    truncated = truncated_likelihood_weights(values.double(), variance.double(), 4, (0.0, 8.0))
    folded = likelihood_weights(values.double(), variance.double(), 4, (0.0, 8.0))
    torch.testing.assert_close(truncated.sum(-1), torch.ones(2, dtype=torch.float64))
    # Interior bins keep their masses' ratios; the edge bins lose the folded tails.
    ratio = truncated[:, 1:3] / folded[:, 1:3]
    torch.testing.assert_close(ratio[:, 0], ratio[:, 1])
    assert (truncated[:, 0] / folded[:, 0] < ratio[:, 0]).all() and (truncated[:, 3] / folded[:, 3] < ratio[:, 0]).all()


def test_truncated_weights_in_the_tails_equal_mpmath():
    mpmath.mp.dps = 60
    bins, value_range = 5, (0.0, 10.0)
    # Each form: erf (across the value), erfc (within 10 standard deviations), log_ndtr (beyond); values inside the
    # clamp (max(8 sigma, 64 sigma^2 / bin width) outside the range), but for the last, one-hot anyway.
    cases = [(-25.0, 1.0), (3.0, 1e-6), (25.0, 1.0), (70.0, 9.0), (5.0, 1e10), (-1e4, 1e6), (13.0, 0.25), (-40.0, 1.0)]
    edges = [mpmath.mpf(edge) for edge in np.linspace(*value_range, bins + 1)]

    def mass(low, high):  # each side where mpmath's ncdf keeps its relative precision
        if high <= 0:
            return mpmath.ncdf(high) - mpmath.ncdf(low)
        if low >= 0:
            return mpmath.ncdf(-low) - mpmath.ncdf(-high)
        return 1 - mpmath.ncdf(low) - mpmath.ncdf(-high)

    for value, var in cases:
        std = mpmath.sqrt(var)
        masses = [mass((low - value) / std, (high - value) / std) for low, high in itertools.pairwise(edges)]
        expected = [float(mpmath.log(m / sum(masses))) for m in masses]
        result = torch.log_softmax(
            _log_bin_masses(
                torch.tensor([value], dtype=torch.float64), torch.tensor([var], dtype=torch.float64), bins, value_range
            ),
            -1,
        )[0]
        # Log weights to 1e-9 wherever they are above 1e-250 (and -inf is never returned).
        relevant = torch.tensor(expected) > (-575 if value > -40 else 0)
        assert torch.isfinite(result).all()
        torch.testing.assert_close(result.exp(), torch.tensor(expected, dtype=torch.float64).exp(), rtol=0, atol=1e-12)
        torch.testing.assert_close(
            result[relevant], torch.tensor(expected, dtype=torch.float64)[relevant], rtol=1e-9, atol=1e-9
        )


@pytest.mark.parametrize("value", [1e6, 1e30])
def test_far_values_and_tiny_variances_stay_finite_and_one_hot(dtype, value):
    values = torch.tensor([value, -value, 5.0, 3.9999], dtype=dtype)
    for var in (1e-30, 1.0, 1e4):
        weights = truncated_likelihood_weights(values, torch.full_like(values, var), 4, (0.0, 8.0))
        assert torch.isfinite(weights).all()
        torch.testing.assert_close(weights[0], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=dtype))
        torch.testing.assert_close(weights[1], torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dtype))
    tiny = truncated_likelihood_weights(values, torch.full_like(values, 1e-30), 4, (0.0, 8.0))
    torch.testing.assert_close(tiny[2:], torch.tensor([[0.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 0.0]], dtype=dtype))


def test_truncated_log_masses_gradcheck_in_every_form():
    # Across the value (erf), within ten standard deviations (erfc), beyond (log_ndtr), below and above the range.
    values = torch.tensor([3.3, 5.0, -2.5, 12.0, -30.0, 50.0], dtype=torch.float64, requires_grad=True)
    variance = torch.tensor([1.0, 0.2, 2.0, 1.5, 4.0, 9.0], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v, s: _log_bin_masses(v, s, 4, (0.0, 8.0)), (values, variance))
