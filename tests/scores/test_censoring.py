"""Saturated readings as censored observations: which readings, each term against integrals, the expansion's order."""

import math

import pytest
import torch
from scipy import integrate, stats

from enmi_torch.scores.censoring import (
    check_saturation,
    saturated_pixels,
    tobit_expansion,
    truncated_moments,
)

RANGE = (0.0, 256.0)


def test_the_value_range_rule_censors_the_ends_only_where_the_image_does_not_read_beyond_them():
    values = torch.tensor(
        [
            [0.0, 0.005, 0.01, 128.0, 255.995, 255.999, 256.0],  # clipped at both ends
            [-3.0, 0.0, 5.0, 128.0, 200.0, 255.999, 256.0],  # reads below 0: 0 is no limit of this image
            [1.0, 5.0, 9.0, 128.0, 200.0, 300.0, 256.0],  # reads above 256: 256 is no limit either
        ],
        dtype=torch.float64,
    )
    valid = torch.ones_like(values, dtype=torch.bool)
    side = saturated_pixels(values, valid, "value_range", RANGE, 32).side  # tolerance: 8 / 1000 grey levels
    assert side.tolist() == [[-1, -1, 0, 0, 1, 1, 1], [0, 0, 0, 0, 0, 1, 1], [0, 0, 0, 0, 0, 0, 0]]
    # An invalid reading neither counts as saturated nor decides whether an end is a limit.
    valid[1, 0] = False
    assert saturated_pixels(values, valid, "value_range", RANGE, 32).side[1].tolist() == [0, -1, 0, 0, 0, 1, 1]
    valid[0, 0] = False
    assert saturated_pixels(values, valid, "value_range", RANGE, 32).side[0, 0] == 0


def test_given_levels_censor_at_and_beyond_them_and_none_censors_nothing():
    values = torch.tensor([[0.0, 1.0, 254.0, 255.0, 300.0]], dtype=torch.float64)
    valid = torch.ones_like(values, dtype=torch.bool)
    assert saturated_pixels(values, valid, (0, 255), RANGE, 32).side.tolist() == [[-1, 0, 0, 1, 1]]
    assert saturated_pixels(values, valid, (None, 255), RANGE, 32).side.tolist() == [[0, 0, 0, 1, 1]]
    assert saturated_pixels(values, valid, (1.0, None), RANGE, 32).side.tolist() == [[-1, -1, 0, 0, 0]]
    nothing = saturated_pixels(values, valid, None, RANGE, 32)
    assert not nothing.any and not bool(nothing.side.any())


@pytest.mark.parametrize(
    ("saturation", "message"),
    [
        ("clip", "saturation must be one of"),
        ((255, 0), r"low < high"),
        ((0, math.inf), "saturation must be 'value_range', None or"),
        ((0, 1, 2), "saturation must be 'value_range', None or"),
        ((True, 255), "saturation must be 'value_range', None or"),
    ],
)
def test_bad_saturation_is_refused_naming_it(saturation, message):
    with pytest.raises(ValueError, match=message):
        check_saturation(saturation)


MEANS = [-40.0, -3.0, 0.0, 2.5, 30.0, 254.0]


@pytest.mark.parametrize("side", [1.0, -1.0])
@pytest.mark.parametrize("mean", MEANS)
def test_the_expansion_matches_the_tail_probability_and_its_first_two_derivatives(mean, side):
    level, variance = 4.0, torch.tensor(9.0, dtype=torch.float64)
    scale = 3.0

    def log_tail(mu: float) -> float:  # the probability of reading beyond the level, by quadrature of the density
        inside_tail = (mu > level) == (side > 0)
        reach = 40 * scale  # beyond 40 standard deviations from where the density is largest, nothing is left
        start = mu if inside_tail else level
        lower, upper = (
            (max(level, start - reach), start + reach) if side > 0 else (start - reach, min(level, start + reach))
        )
        # The density scaled by its value at the tail's nearest point, so that quadrature keeps its digits far out.
        edge = min(max(mu, lower), upper)
        log_edge = stats.norm.logpdf(edge, mu, scale)
        inside = [mu] if lower < mu < upper else None
        value, _ = integrate.quad(
            lambda x: math.exp(stats.norm.logpdf(x, mu, scale) - log_edge),
            lower,
            upper,
            points=inside,
            epsabs=0,
            epsrel=1e-13,
            limit=200,
        )
        return math.log(value) + log_edge

    mu = torch.tensor(mean, dtype=torch.float64)
    pseudo, weight, constant = tobit_expansion(
        mu, variance, torch.tensor(level, dtype=torch.float64), torch.tensor(side)
    )
    # At the expansion point the quadratic is the log-tail; its slope and curvature are the log-tail's.
    assert float(constant - weight / 2 * (pseudo - mu) ** 2) == pytest.approx(log_tail(mean), rel=1e-9, abs=1e-9)
    step = 1e-3
    first = (log_tail(mean + step) - log_tail(mean - step)) / (2 * step)
    second = (log_tail(mean + step) - 2 * log_tail(mean) + log_tail(mean - step)) / step**2
    assert float(weight * (pseudo - mu)) == pytest.approx(first, rel=1e-5, abs=1e-7)
    assert float(-weight) == pytest.approx(second, rel=1e-3, abs=1e-6)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_expansion_stays_finite_and_tends_to_its_limits_far_out(dtype):
    mu = torch.tensor([-1e6, -1e3, 0.0, 1e3, 1e6], dtype=dtype)
    variance, level = torch.tensor(1.0, dtype=dtype), torch.tensor(0.0, dtype=dtype)
    pseudo, weight, constant = tobit_expansion(mu, variance, level, torch.tensor(1.0, dtype=dtype))  # reads >= 0
    assert bool(torch.isfinite(pseudo).all() & torch.isfinite(weight).all() & torch.isfinite(constant[2:]).all())
    # Far below the level the reading acts as an observation at the level of weight 1 / s^2 (a Gaussian value).
    assert float(pseudo[1]) == pytest.approx(0.0, abs=1e-2) and float(weight[1]) == pytest.approx(1.0, rel=1e-5)
    # Far above it the reading says nothing: weight 0, log-probability 0.
    assert float(weight[-1]) == 0.0 and float(constant[-1]) == 0.0


@pytest.mark.parametrize("side", [1.0, -1.0])
@pytest.mark.parametrize("mean", [-6.0, -1.0, 0.5, 7.0])
def test_truncated_moments_equal_numerical_integrals(mean, side):
    level, scale = 1.0, 2.0
    lower, upper = (level, math.inf) if side > 0 else (-math.inf, level)
    mass, _ = integrate.quad(lambda x: stats.norm.pdf(x, mean, scale), lower, upper, epsabs=0, epsrel=1e-12)
    first, _ = integrate.quad(lambda x: x * stats.norm.pdf(x, mean, scale), lower, upper, epsabs=0, epsrel=1e-12)
    second, _ = integrate.quad(lambda x: x * x * stats.norm.pdf(x, mean, scale), lower, upper, epsabs=0, epsrel=1e-12)
    expected_mean = first / mass
    expected_variance = second / mass - expected_mean**2
    as_tensor = {"dtype": torch.float64}
    moments = truncated_moments(
        torch.tensor(mean, **as_tensor),
        torch.tensor(scale**2, **as_tensor),
        torch.tensor(level, **as_tensor),
        torch.tensor(side, **as_tensor),
    )
    assert float(moments[0]) == pytest.approx(expected_mean, rel=1e-8, abs=1e-9)
    assert float(moments[1]) == pytest.approx(expected_variance, rel=1e-6, abs=1e-9)
