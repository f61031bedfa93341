"""The model page (docs/model.md), ECR's Gaussian model: each equation against the library, evaluated directly.

The page's side is float64 NumPy/SciPy and loops over pixels, bins and lags; the scenes are non-square, with a noise
variance that differs per pixel, a non-monotonic response and invalid pixels, so that a swapped axis, a dropped
weight or a dropped term changes the numbers.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _model_page import guards, hard_bin, image, scene
from scipy import optimize, stats

from enmi_torch import ECR, localize
from enmi_torch.functional import ecr, ecr_surface
from enmi_torch.scores.ecr import ecr_model_variance, ecr_surface_model_variance
from enmi_torch.scores.ecr_model_variance import default_model_variance

BINS, VALUE_RANGE = 8, (0.0, 256.0)
FLOOR = ((VALUE_RANGE[1] - VALUE_RANGE[0]) / BINS) ** 2 / 12  # eq-tau-floor


def _inputs(captured, reference, variance, valid, dtype=torch.float64) -> dict:
    """The library's arguments for a scene (invalid pixels hold NaN)."""
    return {
        "captured": image(captured, dtype),
        "reference": image(reference, dtype),
        "variance": image(variance, dtype),
        "valid_mask": torch.tensor(valid)[None, None],
    }


def _bin_sums(values, reference, total_variance, centre=None):
    """eq-ecr-sums by a loop over the pixels: ``W_j``, ``S_j`` (values less ``centre``) and the counts ``N_j``."""
    bins = hard_bin(reference, BINS, VALUE_RANGE)
    weight = 1 / total_variance
    centre = (weight * values).sum() / weight.sum() if centre is None else centre
    weights, sums, counts = np.zeros(BINS), np.zeros(BINS), np.zeros(BINS)
    for n in range(values.size):
        weights[bins[n]] += weight[n]
        sums[bins[n]] += weight[n] * (values[n] - centre)
        counts[bins[n]] += 1
    return weights, sums, counts


def _binned_llr(weights, sums) -> float:
    """eq-ecr-llr: ``(sum_j S_j^2 / W_j - S^2 / W) / 2`` over the occupied bins."""
    occupied = weights > 0
    return 0.5 * ((sums[occupied] ** 2 / weights[occupied]).sum() - sums.sum() ** 2 / weights.sum())


def _binned_ecr(values, reference, total_variance) -> float:
    """eq-ecr-score: ``(LLR - (K_occ - 1) / 2) / N``."""
    weights, sums, counts = _bin_sums(values, reference, total_variance)
    return (_binned_llr(weights, sums) - ((counts > 0).sum() - 1) / 2) / values.size


@guards("eq-ecr-model", "eq-ecr-sums", "eq-ecr-llr", "eq-ecr-score")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_binned_ecr_is_the_gaussian_log_likelihood_ratio(dtype):
    captured, reference, variance, valid = scene(invalid=7)
    captured = captured.astype(np.dtype(str(dtype).removeprefix("torch.")))  # the values the library sees
    tau2 = 37.0
    values, under, total = captured[valid].astype(float), reference[valid], variance[valid] + tau2
    weights, sums, counts = _bin_sums(values, under, total)
    llr = _binned_llr(weights, sums)
    assert llr == pytest.approx(_binned_llr(*_bin_sums(values, under, total, centre=0.0)[:2]), rel=1e-9)
    # eq-ecr-model: both Gaussian models maximised, their log-densities summed pixel by pixel.
    bins = hard_bin(under, BINS, VALUE_RANGE)
    means = {j: np.average(values[bins == j], weights=1 / total[bins == j]) for j in set(bins.tolist())}
    level = np.average(values, weights=1 / total)
    model = sum(stats.norm.logpdf(values[n], means[bins[n]], math.sqrt(total[n])) for n in range(values.size))
    null = sum(stats.norm.logpdf(values[n], level, math.sqrt(total[n])) for n in range(values.size))
    assert llr == pytest.approx(model - null, rel=1e-9)
    expected = (llr - ((counts > 0).sum() - 1) / 2) / values.size
    got = ecr(
        **_inputs(captured, reference, variance, valid, dtype),
        bins=BINS,
        model_variance=tau2,
        response="binned",
        saturation=None,
    )
    assert got.dtype == dtype
    assert got.item() == pytest.approx(expected, rel=1e-12 if dtype == torch.float64 else 1e-6)


@guards("eq-ecr-score")
def test_pure_noise_scores_zero_on_average_whatever_the_variances():
    """``2 LLR`` is chi^2 with ``K_occ - 1`` degrees of freedom: ECR less its penalty has mean 0."""
    generator = np.random.default_rng(11)
    _, reference, variance, _ = scene((6, 10), seed=11)
    samples = 4000
    noise = 100 + np.sqrt(variance) * generator.standard_normal((samples, *variance.shape))
    got = ecr(
        torch.tensor(noise)[:, None],
        torch.tensor(reference)[None, None].expand(samples, 1, *reference.shape),
        torch.tensor(variance)[None, None],
        bins=BINS,
        model_variance=0.0,
        response="binned",
        saturation=None,
    )
    pixels, occupied = reference.size, len(set(hard_bin(reference.ravel(), BINS, VALUE_RANGE).tolist()))
    twice_llr = 2 * pixels * got.numpy() + (occupied - 1)
    assert twice_llr.mean() == pytest.approx(occupied - 1, abs=4 * math.sqrt(2 * (occupied - 1) / samples))
    assert twice_llr.var() == pytest.approx(2 * (occupied - 1), rel=0.15)
    assert abs(got.mean().item()) < 4 * got.std().item() / math.sqrt(samples)


@guards("eq-ecr-eta")
def test_one_variance_gives_the_correlation_ratio():
    captured, reference, _, valid = scene(invalid=5)
    sigma2, tau2 = 150.0, 20.0
    values, bins = captured[valid], hard_bin(reference[valid], BINS, VALUE_RANGE)
    mean = values.mean()
    between = sum((bins == j).sum() * (values[bins == j].mean() - mean) ** 2 for j in set(bins.tolist()))
    eta2 = between / ((values - mean) ** 2).sum()
    spread = ((values - mean) ** 2).mean()
    expected = eta2 * spread / (2 * (sigma2 + tau2)) - (len(set(bins.tolist())) - 1) / (2 * values.size)
    variance = np.full(captured.shape, sigma2)
    got = ecr(**_inputs(captured, reference, variance, valid), bins=BINS, model_variance=tau2, response="binned")
    assert got.item() == pytest.approx(expected, rel=1e-12)


def _linear_llr(values, reference, total_variance) -> float:
    """eq-ecr-linear: ``C_vr^2 / (2 V_rr)`` for an increasing line, else 0."""
    weight = 1 / total_variance
    value_mean, reference_mean = np.average(values, weights=weight), np.average(reference, weights=weight)
    covariance = (weight * (values - value_mean) * (reference - reference_mean)).sum()
    spread = (weight * (reference - reference_mean) ** 2).sum()
    return covariance**2 / (2 * spread) if covariance > 0 else 0.0


@guards("eq-ecr-linear")
@pytest.mark.parametrize("response", ["increasing", "nonmonotonic"])
def test_linear_response_is_the_weighted_regression(response):
    captured, reference, variance, valid = scene(seed=8, response=response, invalid=6)
    if response == "nonmonotonic":
        captured = 300 - captured  # a falling trend: no increasing line, LLR 0
    tau2 = 12.0
    values, under, total = captured[valid], reference[valid], variance[valid] + tau2
    llr = _linear_llr(values, under, total)
    assert (llr > 10) == (response == "increasing")
    got = ecr(**_inputs(captured, reference, variance, valid), bins=BINS, model_variance=tau2, response="linear")
    assert got.item() == pytest.approx((llr - 0.5) / values.size, rel=1e-12)


@guards("eq-ecr-linear-ncc")
def test_linear_response_with_one_variance_is_pearson_squared():
    captured, reference, _, valid = scene(seed=8, response="increasing", invalid=6)
    values, under = captured[valid], reference[valid]
    centred_values, centred_reference = values - values.mean(), under - under.mean()
    rho = (centred_values * centred_reference).sum() / math.sqrt(
        (centred_values**2).sum() * (centred_reference**2).sum()
    )
    sigma2, tau2 = 90.0, 10.0
    expected = rho**2 * (centred_values**2).mean() / (2 * (sigma2 + tau2)) - 1 / (2 * values.size)
    variance = np.full(captured.shape, sigma2)
    got = ecr(**_inputs(captured, reference, variance, valid), bins=BINS, model_variance=tau2, response="linear")
    assert got.item() == pytest.approx(expected, rel=1e-12)


def _shrunk_llr(weights, sums, response_variance: float) -> float:
    """eq-shrunk-llr, term by term, over the occupied bins; ``u_j = j - (K - 1) / 2``."""
    occupied = weights > 0
    weight, value = weights[occupied], sums[occupied]
    position = (np.arange(BINS) - (BINS - 1) / 2)[occupied]
    shrink = 1 / (1 + response_variance * weight)
    pulled = (shrink * weight).sum()
    trend = (shrink * value).sum()
    covariance = (shrink * value * position).sum() - (shrink * weight * position).sum() * trend / pulled
    spread = (shrink * weight * position**2).sum() - (shrink * weight * position).sum() ** 2 / pulled
    twice = (
        response_variance * (shrink * value**2).sum()
        + trend**2 / pulled
        - value.sum() ** 2 / weight.sum()
        + (covariance**2 / spread if covariance > 0 else 0.0)
        - np.log1p(response_variance * weight).sum()
    )
    return twice / 2


@guards("eq-shrunk-llr")
@pytest.mark.parametrize("response_variance", [0.0, 3.0, 500.0, 1e5])
@pytest.mark.parametrize("response", ["increasing", "nonmonotonic"])
def test_shrunk_llr_term_by_term(response, response_variance):
    captured, reference, variance, valid = scene(seed=9, response=response, invalid=4)
    tau2 = 25.0
    weights, sums, _ = _bin_sums(captured[valid], reference[valid], variance[valid] + tau2)
    expected = (_shrunk_llr(weights, sums, response_variance) - 0.5) / valid.sum()
    got = ecr(
        **_inputs(captured, reference, variance, valid),
        bins=BINS,
        model_variance=tau2,
        response="shrunk",
        response_variance=response_variance,
        saturation=None,
    )
    assert got.item() == pytest.approx(expected, rel=1e-10)


@guards("eq-shrunk-model", "eq-shrunk-llr")
@pytest.mark.parametrize("response_variance", [0.0, 40.0, 2000.0])
@pytest.mark.parametrize("response", ["increasing", "nonmonotonic"])
def test_shrunk_llr_is_the_marginal_likelihood_ratio_of_its_model(response, response_variance):
    """The deviations integrated out of the pixels' joint density: ``v ~ N(a + b u_j, diag(s^2) + delta^2 Z Z')``."""
    captured, reference, variance, _ = scene((6, 9), seed=10, response=response)
    tau2 = 30.0
    values, total = captured.ravel(), variance.ravel() + tau2
    bins = hard_bin(reference.ravel(), BINS, VALUE_RANGE)
    positions = bins - (BINS - 1) / 2
    covariance = np.diag(total) + response_variance * (bins[:, None] == bins[None, :])

    def best_log_density(design, covariance):
        precision = np.linalg.inv(covariance)
        beta = np.linalg.solve(design.T @ precision @ design, design.T @ precision @ values)
        return stats.multivariate_normal.logpdf(values, design @ beta, covariance), beta

    line = np.stack([np.ones_like(values), positions], 1)
    model, beta = best_log_density(line, covariance)
    if beta[1] < 0:  # b >= 0: a falling trend is the flat line
        model, _ = best_log_density(line[:, :1], covariance)
    null, _ = best_log_density(line[:, :1], np.diag(total))
    weights, sums, _ = _bin_sums(values, reference.ravel(), total)
    assert _shrunk_llr(weights, sums, response_variance) == pytest.approx(model - null, rel=1e-9, abs=1e-9)
    got = ecr(
        image(captured),
        image(reference),
        image(variance),
        bins=BINS,
        model_variance=tau2,
        response_variance=response_variance,
        saturation=None,
    )
    assert got.item() == pytest.approx((model - null - 0.5) / values.size, rel=1e-9)


@guards("eq-shrunk-delta")
@pytest.mark.parametrize("response", ["increasing", "nonmonotonic"])
def test_estimated_response_variance_maximises_the_profile(response):
    captured, reference, variance, valid = scene((12, 17), seed=12, response=response, invalid=5)
    tau2 = 40.0
    weights, sums, _ = _bin_sums(captured[valid], reference[valid], variance[valid] + tau2)
    span = (VALUE_RANGE[1] - VALUE_RANGE[0]) ** 2
    grid = [0.0, *(span * 10.0**k for k in np.linspace(-8, 1, 901))]
    best = max(_shrunk_llr(weights, sums, delta2) for delta2 in grid)
    score = ECR(bins=BINS, model_variance=tau2, saturation=None)
    inputs = _inputs(captured, reference, variance, valid)
    delta2 = score.response_variance_of(
        inputs["captured"], inputs["reference"], inputs["variance"], valid_mask=inputs["valid_mask"]
    ).item()
    assert _shrunk_llr(weights, sums, delta2) >= best - 0.03  # "within a few hundredths of a nat"
    got = score(inputs["captured"], inputs["reference"], inputs["variance"], valid_mask=inputs["valid_mask"])
    assert got.item() == pytest.approx((_shrunk_llr(weights, sums, delta2) - 0.5) / valid.sum(), rel=1e-10)
    assert (delta2 > 1e3) == (response == "nonmonotonic")  # the V leaves the line, the near-line keeps to it


@guards("eq-tau-floor")
def test_model_variance_is_at_least_the_quantisation():
    assert default_model_variance(BINS, VALUE_RANGE) == pytest.approx(FLOOR, rel=1e-15)
    captured, reference, variance, valid = scene(invalid=3)
    got = ecr(**_inputs(captured, reference, variance, valid), bins=BINS, model_variance=None, response="binned")
    assert got.item() == pytest.approx(_binned_ecr(captured[valid], reference[valid], variance[valid] + FLOOR))
    # A pair the bins explain up to the stated noise: REML's maximum lies below the floor, which is taken.
    few_bins = 4
    centres = np.array([32.0, 96.0, 160.0, 224.0])
    generator = np.random.default_rng(13)
    on_centres = centres[generator.integers(0, few_bins, (8, 13))]
    small = np.outer(np.linspace(1, 25, 8), np.ones(13))
    noisy = 255 - on_centres + np.sqrt(small) * generator.standard_normal(small.shape)
    tau2 = ecr_model_variance(image(noisy), image(on_centres), image(small), bins=few_bins, saturation=None)
    assert tau2.item() == pytest.approx(64.0**2 / 12, rel=1e-15)


def _design(reference: np.ndarray, response: str) -> np.ndarray:
    """The fitted means' columns: one per occupied bin, or ``[1, r]``."""
    if response == "linear":
        return np.stack([np.ones_like(reference), reference], 1)
    bins = hard_bin(reference, BINS, VALUE_RANGE)
    return (bins[:, None] == np.unique(bins)[None, :]).astype(float)


def _restricted_log_likelihood(tau2, values, noise, design) -> float:
    """eq-reml-likelihood."""
    weight = 1 / (noise + tau2)
    information = design.T @ (weight[:, None] * design)
    residual = values - design @ np.linalg.solve(information, design.T @ (weight * values))
    return -0.5 * (np.log(noise + tau2).sum() + np.linalg.slogdet(information)[1] + (weight * residual**2).sum())


def _reml_score(tau2, values, noise, design) -> tuple[float, float]:
    """eq-reml-score: ``U`` and ``I``."""
    weight = 1 / (noise + tau2)
    information = design.T @ (weight[:, None] * design)
    residual = values - design @ np.linalg.solve(information, design.T @ (weight * values))
    trace = np.trace(np.linalg.solve(information, design.T @ ((weight**2)[:, None] * design)))
    return 0.5 * ((weight**2 * residual**2).sum() - weight.sum() + trace), 0.5 * (weight**2).sum()


@guards("eq-reml-likelihood", "eq-reml-score")
@pytest.mark.parametrize("response", ["binned", "shrunk", "linear"])
def test_model_variance_is_the_reml_estimate(response):
    captured, reference, variance, valid = scene(seed=14, misfit=25.0, invalid=6)
    values, under, noise = captured[valid], reference[valid], variance[valid]
    design = _design(under, response)
    found = optimize.minimize_scalar(
        lambda tau2: -_restricted_log_likelihood(tau2, values, noise, design),
        bounds=(FLOOR, 1e5),
        method="bounded",
        options={"xatol": 1e-9},
    ).x
    inputs = _inputs(captured, reference, variance, valid)
    got = ecr_model_variance(**inputs, bins=BINS, response=response, saturation=None).item()
    assert got > 5 * FLOOR
    assert got == pytest.approx(found, rel=1e-7)
    score, information = _reml_score(got, values, noise, design)
    assert abs(score / information) < 1e-8 * got  # a root of the REML score: Fisher scoring has settled
    assert abs(_reml_score(1.1 * got, values, noise, design)[0]) > 1e3 * abs(score)
    total = noise + got
    value = ecr(**inputs, bins=BINS, response=response, saturation=None)
    if response == "linear":
        assert value.item() == pytest.approx((_linear_llr(values, under, total) - 0.5) / values.size, rel=1e-10)
    elif response == "binned":
        assert value.item() == pytest.approx(_binned_ecr(values, under, total), rel=1e-10)


def _fitted_residuals(values, reference, total_variance) -> np.ndarray:
    """Values less their weighted bin means, a loop per bin."""
    bins = hard_bin(reference, BINS, VALUE_RANGE)
    residual = np.empty_like(values)
    for j in set(bins.tolist()):
        here = bins == j
        residual[here] = values[here] - np.average(values[here], weights=1 / total_variance[here])
    return residual


def _blocks(shape, size, generator) -> np.ndarray:
    rows, cols = -(-shape[0] // size), -(-shape[1] // size)
    return np.kron(generator.standard_normal((rows, cols)), np.ones((size, size)))[: shape[0], : shape[1]]


@guards("eq-misfit-correlated")
def test_correlated_misfit_counts_the_misfit_per_block():
    captured, reference, variance, valid = scene((24, 33), seed=15)
    captured = captured + 30 * _blocks(captured.shape, 3, np.random.default_rng(15))
    inputs = _inputs(captured, reference, variance, valid)
    tau2 = ecr_model_variance(**inputs, bins=BINS, saturation=None).item()
    height, width = captured.shape
    residual = _fitted_residuals(captured.ravel(), reference.ravel(), variance.ravel() + tau2).reshape(height, width)
    residual = residual - residual.mean()
    reach = max(1, round(min(height, width) / 8))
    summed = 0.0
    for lag_y in range(-min(reach, height - 1), min(reach, height - 1) + 1):
        for lag_x in range(-min(reach, width - 1), min(reach, width - 1) + 1):
            if lag_y == lag_x == 0:
                continue
            products = [
                residual[y, x] * residual[y + lag_y, x + lag_x]
                for y in range(height)
                for x in range(width)
                if 0 <= y + lag_y < height and 0 <= x + lag_x < width
            ]
            taper = (1 - abs(lag_y) / (reach + 1)) * (1 - abs(lag_x) / (reach + 1))
            summed += taper * np.mean(products)
    extent = min(height * width, max(1.0, 1 + summed / tau2))
    assert 3 < extent < 9  # 3 x 3 blocks, tapered
    expected = FLOOR + extent * (tau2 - FLOOR)
    got = ecr_model_variance(**inputs, bins=BINS, saturation=None, misfit="correlated")
    assert got.item() == pytest.approx(expected, rel=1e-10)
    value = ecr(**inputs, bins=BINS, response="binned", misfit="correlated", saturation=None)
    assert value.item() == pytest.approx(_binned_ecr(captured.ravel(), reference.ravel(), variance.ravel() + expected))


@guards("eq-misfit-regional")
def test_regional_misfit_reads_a_shrunk_local_estimate():
    captured, reference, variance, valid = scene((20, 29), seed=16, misfit=5.0)
    captured[3:10, 5:17] += 60 * np.random.default_rng(16).standard_normal((7, 12))  # a changed patch
    inputs = _inputs(captured, reference, variance, valid)
    tau2 = ecr_model_variance(**inputs, bins=BINS, saturation=None).item()
    height, width = captured.shape
    reach_y, reach_x = max(1, round(height / 8)), max(1, round(width / 8))
    values, noise = captured.ravel(), variance.ravel()
    previous = np.full(values.size, tau2)
    for _ in range(2):
        residual = _fitted_residuals(values, reference.ravel(), noise + previous)
        precision = (1 / (noise + previous) ** 2).reshape(height, width)
        excess = (residual**2 - noise).reshape(height, width)
        local, sampling = np.empty((height, width)), np.empty((height, width))
        for y in range(height):
            for x in range(width):
                box = slice(max(0, y - reach_y), y + reach_y + 1), slice(max(0, x - reach_x), x + reach_x + 1)
                local[y, x] = (precision[box] * excess[box]).sum() / precision[box].sum()
                sampling[y, x] = 2 / precision[box].sum()
        spread = max(0.0, ((local - tau2) ** 2 - sampling).mean())
        previous = np.maximum(FLOOR, tau2 + spread / (spread + sampling) * (local - tau2)).ravel()
    got = ecr_model_variance(**inputs, bins=BINS, saturation=None, misfit="regional")[0].numpy()
    np.testing.assert_allclose(got.ravel(), previous, rtol=1e-10)
    assert previous.reshape(height, width)[6, 10] > 5 * previous.reshape(height, width)[1, 25] > 5 * FLOOR
    value = ecr(**inputs, bins=BINS, response="binned", misfit="regional", saturation=None)
    assert value.item() == pytest.approx(_binned_ecr(values, reference.ravel(), noise + previous), rel=1e-10)


def _window_scene():
    """A smooth map, a non-square crop of it through a sensor that saturates, a variance growing down the rows."""
    generator = torch.Generator().manual_seed(2)
    reference = torch.rand(1, 1, 40, 52, generator=generator, dtype=torch.float64) * 256
    reference = torch.nn.functional.avg_pool2d(reference, 3, 1, 1)
    height, width, top, left = 14, 19, 12, 20
    variance = torch.linspace(20, 400, height, dtype=torch.float64)[:, None].expand(height, width).contiguous()
    noise = torch.randn(1, 1, height, width, generator=generator, dtype=torch.float64)
    crop = reference[..., top : top + height, left : left + width]
    low, high = crop.quantile(0.1).item(), crop.quantile(0.9).item()  # a contrast that clips about a fifth
    captured = ((crop - low) * 255 / (high - low) + variance.sqrt() * noise).clamp(0, 255)
    saturated = ((captured == 0) | (captured == 255)).double().mean()
    assert 0.1 < saturated < 0.4, saturated
    return captured, reference, variance


@guards("eq-ecr-surface")
def test_surface_is_ecr_with_the_model_fitted_once():
    captured, reference, variance = _window_scene()
    window = reference[..., 8:30, 14:43]
    score = ECR(bins=BINS, saturation=(0, 255))
    surface = score.surface(captured, window, variance).score[0]
    tau2 = ecr_surface_model_variance(captured, window, variance, bins=BINS, saturation=(0, 255)).item()
    delta2 = score.surface_response_variance(captured, window, variance).item()
    height, width = captured.shape[2:]
    assert surface.shape == (window.shape[2] - height + 1, window.shape[3] - width + 1)
    differs = []
    for row in range(surface.shape[0]):
        for col in range(surface.shape[1]):
            crop = window[..., row : row + height, col : col + width]
            fixed = ecr(
                captured, crop, variance, bins=BINS, model_variance=tau2, response_variance=delta2, saturation=None
            )
            assert surface[row, col].item() == pytest.approx(fixed.item(), rel=1e-7, abs=1e-9)
            if row % 3 == col % 3 == 0:  # its own fit and the censored readings change the value
                differs.append(abs(score(captured, crop, variance).item() - fixed.item()) > 1e-6)
    assert sum(differs) > len(differs) // 2
    assert ecr_surface(captured, window, variance, bins=BINS, saturation=(0, 255)).score[0].equal(surface)


@guards("eq-finalists")
def test_search_answers_with_the_best_exact_score_of_its_finalists():
    captured, reference, variance = _window_scene()
    score = ECR(bins=BINS, saturation=(0, 255))
    radius = (4, 5)
    found = localize(captured, reference, variance, score=score, shifts=radius)
    surface = found.surface[0, 0]
    height, width = captured.shape[2:]
    top, left = reference.shape[2] // 2 - height // 2, reference.shape[3] // 2 - width // 2
    # The surface's local maxima (at least their 3 x 3 neighbours), best first, by a loop.
    maxima = []
    for row in range(surface.shape[0]):
        for col in range(surface.shape[1]):
            around = surface[max(0, row - 1) : row + 2, max(0, col - 1) : col + 2]
            if torch.isfinite(surface[row, col]) and surface[row, col] >= around.max():
                maxima.append((surface[row, col].item(), row, col))
    maxima.sort(key=lambda peak: -peak[0])
    finalists = found.finalists
    count = finalists.placements.shape[1]
    assert count == 8
    assert [tuple(p) for p in finalists.placements[0].tolist()] == [(0, row, col) for _, row, col in maxima[:count]]
    exact = []
    for _, row, col in maxima[:count]:
        crop = reference[..., top + row - radius[0] : top + row - radius[0] + height, :]
        crop = crop[..., left + col - radius[1] : left + col - radius[1] + width]
        exact.append(score(captured, crop, variance).item())
    np.testing.assert_allclose(finalists.scores[0].numpy(), exact, rtol=1e-9)
    assert finalists.chosen.item() == int(np.argmax(exact))
    assert any(abs(e - s[0]) > 1e-4 for e, s in zip(exact, maxima[:count], strict=True))  # each fitted anew
