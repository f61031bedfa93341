"""The model page (docs/model.md), saturated readings: the censored (Tobit) model against the library.

The page's side evaluates the censored likelihood itself: the probability beyond a reading by numerical integration
of the Gaussian density (``scipy.integrate.quad``), its modes by SciPy's optimisers, its Laplace approximation and
its EM estimate by loops, on clipped non-square scenes with a variance that differs per pixel.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _model_page import guards, hard_bin, image, scene
from scipy import integrate, optimize, special, stats

from enmi_torch.functional import ecr
from enmi_torch.scores.censoring import saturated_pixels, tobit_expansion, truncated_moments
from enmi_torch.scores.ecr import ecr_model_variance

BINS, VALUE_RANGE, LEVELS = 6, (0.0, 256.0), (0.0, 255.0)
FLOOR = ((VALUE_RANGE[1] - VALUE_RANGE[0]) / BINS) ** 2 / 12


def _clipped(shape=(7, 11), seed=7, response="increasing", misfit=0.0):
    """A scene read through a sensor that clips at 0 and 255: about a sixth of the readings saturated."""
    captured, reference, variance, _ = scene(shape, seed=seed, response=response, misfit=misfit)
    captured = np.clip(1.25 * captured - 30, *LEVELS)
    side = np.where(captured >= LEVELS[1], 1.0, np.where(captured <= LEVELS[0], -1.0, 0.0))
    assert 0.08 < (side != 0).mean() < 0.45 and (side > 0).any() and (side < 0).any()
    return captured.ravel(), reference.ravel(), variance.ravel(), side.ravel()


def _mills(z: np.ndarray) -> np.ndarray:
    """``lambda = phi(z) / Phi(z)`` by SciPy: ``sqrt(2 / pi) / erfcx(-z / sqrt 2)`` below 0 (no underflow)."""
    z = np.asarray(z, dtype=float)
    below = math.sqrt(2 / math.pi) / special.erfcx(-np.minimum(z, 0.0) / math.sqrt(2))
    above = np.maximum(z, 0.0)
    return np.where(z < 0, below, stats.norm.pdf(above) / special.ndtr(above))


def _log_terms(mean, values, total, side) -> np.ndarray:
    """Each pixel's log-likelihood: eq-tobit-term where saturated (SciPy's log CDF), else the Gaussian's exponent."""
    z = side * (mean - values) / np.sqrt(total)
    return np.where(side != 0, special.log_ndtr(z), -0.5 * (values - mean) ** 2 / total)


def _shifted_integral(bound: float) -> float:
    """``int_0^inf exp(-b t - t^2 / 2) dt`` by quadrature: ``P(X > b) = phi(b)`` times it, ``X ~ N(0, 1)``."""
    return integrate.quad(lambda t: math.exp(-bound * t - t * t / 2), 0, np.inf, epsabs=0, epsrel=1e-13)[0]


def _log_tail(bound: float) -> float:
    """``log P(X > b)`` for any ``b``, integrated from the density (no underflow far in the tail)."""
    if bound > 0:
        return stats.norm.logpdf(bound) + math.log(_shifted_integral(bound))
    return math.log1p(-stats.norm.pdf(-bound) * _shifted_integral(-bound))


def _log_likelihood_by_quadrature(mean, values, total, side) -> float:
    """eq-tobit-term by quadrature: ``log P(x beyond the reading)`` integrated from the Gaussian density."""
    out = 0.0
    for n in range(values.size):
        if side[n] == 0:
            out += -0.5 * (values[n] - mean[n]) ** 2 / total[n]
        else:  # beyond an upper reading: P(X > (v - mu) / s); below a lower one: P(X > (mu - v) / s)
            out += _log_tail(side[n] * (values[n] - mean[n]) / math.sqrt(total[n]))
    return out


def _best_level(values, total, side, start: float) -> float:
    """The one mean that maximises the censored likelihood of ``values`` (SciPy's Brent search)."""
    found = optimize.minimize_scalar(
        lambda level: -_log_terms(level, values, total, side).sum(), bracket=(start - 5, start + 5), tol=1e-12
    )
    return float(found.x)


def _expansion(mean, values, total, side):
    """eq-tobit-expansion: pseudo-observations, weights and constants; the readings as they are elsewhere."""
    scale = np.sqrt(total)
    z = side * (mean - values) / scale
    mills = _mills(z)
    weight = np.where(side != 0, mills * (mills + z) / total, 1 / total)
    pseudo = np.where(side != 0, mean + side * scale / (mills + z), values)
    constant = np.where(side != 0, special.log_ndtr(z) + mills / (2 * (mills + z)), 0.0)
    return pseudo, weight, constant


def _spread(pseudo, weight) -> float:
    """``SS``: the weighted sum of squares about the weighted mean."""
    return (weight * (pseudo - np.average(pseudo, weights=weight)) ** 2).sum()


def _bin_sums(pseudo, weight, bins):
    centre = np.average(pseudo, weights=weight)
    return np.bincount(bins, weight, BINS), np.bincount(bins, weight * (pseudo - centre), BINS)


def _corrected_llr(gaussian_llr, modes, values, total, side) -> float:
    """eq-censored-llr from the pseudo-observations at the two modes (``modes``: null, response)."""
    null, response = (_expansion(mode, values, total, side) for mode in modes)
    return (
        gaussian_llr(*response[:2])
        + 0.5 * (_spread(*null[:2]) - _spread(*response[:2]))
        + (response[2] - null[2]).sum()
    )


def _ecr(values, reference, variance, tau2, response, **options) -> float:
    shape = (1, 1, 1, values.size)
    return ecr(
        torch.tensor(values).view(shape),
        torch.tensor(reference).view(shape),
        torch.tensor(variance).view(shape),
        bins=BINS,
        model_variance=tau2,
        response=response,
        saturation=LEVELS,
        **options,
    ).item()


@guards("eq-saturation")
def test_which_readings_are_saturated():
    width = (VALUE_RANGE[1] - VALUE_RANGE[0]) / BINS
    rows = np.array(
        [
            [0.0, 1e-3 * width, 0.01, 100.0, 256.0 - 1e-3 * width, 255.9, 256.0],  # both ends are limits
            [-0.5, 0.0, 0.01, 100.0, 255.99, 256.0, 256.0],  # reads below 0: only the upper end is a limit
            [0.0, 0.02, 50.0, 100.0, 200.0, 255.99, 300.0],  # reads above 256: only the lower end
        ]
    )
    tolerance = 1e-3 * width
    expected = np.zeros_like(rows)
    for row, values in enumerate(rows):
        for n, value in enumerate(values):
            if value >= VALUE_RANGE[1] - tolerance and values.max() <= VALUE_RANGE[1]:
                expected[row, n] = 1
            elif value <= VALUE_RANGE[0] + tolerance and values.min() >= VALUE_RANGE[0]:
                expected[row, n] = -1
    assert expected.tolist() == [[-1, -1, -1, 0, 1, 0, 1], [0, 0, 0, 0, 1, 1, 1], [-1, -1, 0, 0, 0, 0, 0]]
    readings = torch.tensor(rows)
    valid = torch.ones_like(readings, dtype=torch.bool)
    got = saturated_pixels(readings, valid, "value_range", VALUE_RANGE, BINS)
    assert got.side.tolist() == expected.tolist() and got.any
    levels = saturated_pixels(readings, valid, (0.0, 255.99), VALUE_RANGE, BINS).side
    assert levels.tolist() == np.where(rows >= 255.99, 1, np.where(rows <= 0, -1, 0)).tolist()


@guards("eq-tobit-expansion")
@pytest.mark.parametrize("side", [1.0, -1.0])
def test_a_saturated_term_expanded_to_second_order(side):
    limit, total = 255.0, 49.0
    offsets = np.array([-300.0, -60.0, -7.0, -1.0, 0.0, 2.0, 9.0, 25.0])  # mean - limit, on the upper side
    mean = limit + side * offsets
    pseudo, weight, constant = _expansion(
        mean, np.full_like(mean, limit), np.full_like(mean, total), np.full_like(mean, side)
    )
    got = tobit_expansion(*(torch.tensor(part, dtype=torch.float64) for part in (mean, total, limit, side)))
    np.testing.assert_allclose(got[0].numpy(), pseudo, rtol=1e-8)
    np.testing.assert_allclose(got[1].numpy(), weight, rtol=1e-8)
    # c is log Phi plus a term of nearly its size, 40 standard deviations off: absolute round-off of that size.
    log_phi = special.log_ndtr(side * (mean - limit) / math.sqrt(total))
    np.testing.assert_allclose(got[2].numpy(), constant, rtol=1e-8, atol=1e-12 * np.abs(log_phi).max())
    # Value, slope and curvature of log Phi at the expansion point, by SciPy and central differences.
    step = 1e-3 * math.sqrt(total)
    for k in range(mean.size):

        def exact(mu, k=k):
            return special.log_ndtr(side * (mu - limit) / math.sqrt(total))

        def quadratic(mu, k=k):
            return constant[k] - weight[k] / 2 * (pseudo[k] - mu) ** 2

        here = mean[k]
        for function in (exact, quadratic):
            assert function(here) == pytest.approx(exact(here), rel=1e-12, abs=1e-300)
        slopes = [(f(here + step) - f(here - step)) / (2 * step) for f in (exact, quadratic)]
        curvatures = [(f(here + step) - 2 * f(here) + f(here - step)) / step**2 for f in (exact, quadratic)]
        assert slopes[1] == pytest.approx(slopes[0], rel=1e-5, abs=1e-12)
        assert curvatures[1] == pytest.approx(curvatures[0], rel=1e-3, abs=1e-9)


@guards("eq-tobit-term", "eq-censored-llr")
def test_binned_censored_ecr_is_the_exact_tobit_likelihood_ratio():
    values, reference, variance, side = _clipped()
    tau2 = 40.0
    total = variance + tau2
    bins = hard_bin(reference, BINS, VALUE_RANGE)
    null = np.full(values.size, _best_level(values, total, side, values.mean()))
    response = np.empty(values.size)
    for j in np.unique(bins):
        here = bins == j
        response[here] = _best_level(values[here], total[here], side[here], values[here].mean())
    exact = _log_likelihood_by_quadrature(response, values, total, side)
    exact -= _log_likelihood_by_quadrature(null, values, total, side)

    def binned_llr(pseudo, weight):  # eq-ecr-llr on the pseudo-observations' sums
        weights, sums = _bin_sums(pseudo, weight, bins)
        occupied = weights > 0
        return 0.5 * ((sums[occupied] ** 2 / weights[occupied]).sum() - sums.sum() ** 2 / weights.sum())

    formula = _corrected_llr(binned_llr, (null, response), values, total, side)
    assert formula == pytest.approx(exact, rel=1e-9)
    penalty = (len(np.unique(bins)) - 1) / 2
    got = _ecr(values, reference, variance, tau2, "binned")
    assert got == pytest.approx((exact - penalty) / values.size, rel=1e-9)
    gaussian = ecr(
        image(values[None]),
        image(reference[None]),
        image(variance[None]),
        bins=BINS,
        model_variance=tau2,
        response="binned",
        saturation=None,
    )
    assert abs(got - gaussian.item()) > 1e-2  # the censored terms matter here


@guards("eq-tobit-term", "eq-censored-llr")
def test_linear_censored_ecr_is_the_exact_tobit_likelihood_ratio():
    values, reference, variance, side = _clipped(seed=17)
    tau2 = 30.0
    total = variance + tau2
    null = np.full(values.size, _best_level(values, total, side, values.mean()))
    centred = reference - reference.mean()

    def negative(parameters):
        return -_log_terms(parameters[0] + parameters[1] * centred, values, total, side).sum()

    found = optimize.minimize(
        negative,
        [values.mean(), 1.0],
        method="L-BFGS-B",
        bounds=[(None, None), (0, None)],
        options={"ftol": 1e-15, "gtol": 1e-11},
    )
    found = optimize.minimize(negative, found.x, method="Nelder-Mead", options={"xatol": 1e-10, "fatol": 1e-14})
    response = found.x[0] + max(found.x[1], 0.0) * centred
    exact = _log_likelihood_by_quadrature(response, values, total, side)
    exact -= _log_likelihood_by_quadrature(null, values, total, side)

    def linear_llr(pseudo, weight):  # eq-ecr-linear on the pseudo-observations
        value_mean, reference_mean = np.average(pseudo, weights=weight), np.average(reference, weights=weight)
        covariance = (weight * (pseudo - value_mean) * (reference - reference_mean)).sum()
        return covariance**2 / (2 * (weight * (reference - reference_mean) ** 2).sum()) if covariance > 0 else 0.0

    assert _corrected_llr(linear_llr, (null, response), values, total, side) == pytest.approx(exact, rel=1e-7)
    assert _ecr(values, reference, variance, tau2, "linear") == pytest.approx((exact - 0.5) / values.size, rel=1e-7)


@guards("eq-censored-llr")
@pytest.mark.parametrize("response", ["increasing", "nonmonotonic"])
@pytest.mark.parametrize("response_variance", [150.0, 5000.0])
def test_shrunk_censored_ecr_is_laplace_at_the_joint_mode(response, response_variance):
    """``max_{a, b >= 0, d} [sum_n l_n(a + b u + d) - |d|^2 / 2 delta^2] - 1/2 sum_j log(1 + delta^2 H_j)``."""
    values, reference, variance, side = _clipped(seed=19, response=response)
    tau2 = 40.0
    total = variance + tau2
    bins = hard_bin(reference, BINS, VALUE_RANGE)
    occupied = np.unique(bins)
    column = np.searchsorted(occupied, bins)
    position = (occupied - (BINS - 1) / 2)[column]
    censored = side != 0

    def slope_and_curvature(mean):
        z = side * (mean - values) / np.sqrt(total)
        mills = _mills(z)
        slope = np.where(censored, side * mills / np.sqrt(total), (values - mean) / total)
        return slope, np.where(censored, mills * (mills + z) / total, 1 / total)

    def negative(parameters):
        level, trend, deviations = parameters[0], parameters[1], parameters[2:]
        mean = level + trend * position + deviations[column]
        slope, _ = slope_and_curvature(mean)
        value = _log_terms(mean, values, total, side).sum() - (deviations**2).sum() / (2 * response_variance)
        gradient = [slope.sum(), (slope * position).sum()]
        gradient += list(np.bincount(column, slope, occupied.size) - deviations / response_variance)
        return -value, -np.array(gradient)

    start = np.concatenate([[values.mean(), 1.0], np.zeros(occupied.size)])
    bounds = [(None, None), (0, None)] + [(None, None)] * occupied.size
    found = optimize.minimize(
        negative,
        start,
        jac=True,
        method="L-BFGS-B",
        bounds=bounds,
        options={"ftol": 1e-16, "gtol": 1e-12, "maxiter": 20000},
    )
    mode = found.x[0] + found.x[1] * position + found.x[2:][column]
    curvature = np.bincount(column, slope_and_curvature(mode)[1], occupied.size)
    laplace = -found.fun - 0.5 * np.log1p(response_variance * curvature).sum()
    null = _best_level(values, total, side, values.mean())
    llr = laplace - _log_terms(null, values, total, side).sum()
    got = _ecr(values, reference, variance, tau2, "shrunk", response_variance=response_variance)
    assert got == pytest.approx((llr - 0.5) / values.size, rel=1e-8)


@guards("eq-censored-llr")
def test_without_a_saturated_reading_the_censored_model_is_the_gaussian():
    captured, reference, variance, _ = scene((8, 13), seed=21)
    captured = 0.6 * captured + 50
    assert 0 < captured.min() and captured.max() < 255
    for response in ("binned", "linear", "shrunk"):
        censored = _ecr(captured.ravel(), reference.ravel(), variance.ravel(), 30.0, response)
        gaussian = ecr(
            image(captured),
            image(reference),
            image(variance),
            bins=BINS,
            model_variance=30.0,
            response=response,
            saturation=None,
        )
        assert censored == pytest.approx(gaussian.item(), rel=1e-12)


@guards("eq-truncated-moments")
@pytest.mark.parametrize("side", [1.0, -1.0])
@pytest.mark.parametrize("offset", [-40.0, -3.0, 0.0, 5.0, 30.0])
def test_moments_beyond_the_limit_by_quadrature(side, offset):
    limit, total = 255.0, 36.0
    mean, scale = limit + side * offset, math.sqrt(total)
    bounds = (limit, np.inf) if side > 0 else (-np.inf, limit)
    moments = [
        integrate.quad(
            lambda x, p=p: x**p * stats.norm.pdf(x, mean, scale), *bounds, epsabs=0, epsrel=1e-13, limit=200
        )[0]
        for p in range(3)
    ]
    expected_mean = moments[1] / moments[0]
    expected_variance = moments[2] / moments[0] - expected_mean**2
    z = side * (mean - limit) / scale
    mills = _mills(np.array(z))
    page_mean, page_variance = mean + side * scale * mills, total * (1 - mills * (mills + z))
    assert page_mean == pytest.approx(expected_mean, rel=1e-10)
    assert page_variance == pytest.approx(expected_variance, rel=1e-6)
    got = truncated_moments(*(torch.tensor(part, dtype=torch.float64) for part in (mean, total, limit, side)))
    assert got[0].item() == pytest.approx(page_mean, rel=1e-12)
    assert got[1].item() == pytest.approx(page_variance, rel=1e-9)


def _fit(values, weight, design):
    """The weighted least-squares fit and ``tr((X'WX)^-1 X'W^2 X)``."""
    information = design.T @ (weight[:, None] * design)
    fitted = design @ np.linalg.solve(information, design.T @ (weight * values))
    return fitted, np.trace(np.linalg.solve(information, design.T @ ((weight**2)[:, None] * design)))


@guards("eq-em-tau")
@pytest.mark.parametrize("response", ["binned", "linear"])
def test_model_variance_by_expectation_maximisation(response):
    values, reference, variance, side = _clipped((13, 18), seed=23, misfit=25.0)
    if response == "linear":
        design = np.stack([np.ones_like(reference), reference], 1)
    else:
        bins = hard_bin(reference, BINS, VALUE_RANGE)
        design = (bins[:, None] == np.unique(bins)[None, :]).astype(float)
    censored = side != 0
    tau2, mean = 100.0, _fit(values, np.ones_like(values), design)[0]
    for _ in range(500):
        total = variance + tau2
        weight, scale = 1 / total, np.sqrt(total)
        z = side * (mean - values) / scale
        mills = _mills(z)
        completed = np.where(censored, mean + side * scale * mills, values)  # eq-truncated-moments
        extra = np.where(censored, total * (1 - mills * (mills + z)), 0.0)
        mean, trace = _fit(completed, weight, design)
        score = 0.5 * ((weight**2 * ((completed - mean) ** 2 + extra)).sum() - weight.sum() + trace)
        updated = max(FLOOR, tau2 + score / (0.5 * (weight**2).sum()))
        settled = abs(updated - tau2) <= 1e-13 * updated
        tau2 = updated
        if settled:
            break
    assert settled and tau2 > 5 * FLOOR
    shape = (1, 1, 1, values.size)
    inputs = [torch.tensor(part).view(shape) for part in (values, reference, variance)]
    got = ecr_model_variance(*inputs, bins=BINS, response=response, saturation=LEVELS).item()
    assert got == pytest.approx(tau2, rel=1e-5)  # the library's EM stops when tau^2 moves by a millionth
    gaussian = ecr_model_variance(*inputs, bins=BINS, response=response, saturation=None).item()
    assert gaussian < 0.9 * got  # read as Gaussian values, the clipped readings bias the estimate low
