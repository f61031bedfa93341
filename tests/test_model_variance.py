import pytest
import torch

from enmi_torch import _model_variance as model_variance
from enmi_torch.binning import hard_bin_index
from enmi_torch.localization.surface import _check_inputs, ecr_surface

BINS = 8
RANGE = (0.0, 256.0)


def _aligned(tau2: float, generator, batch=6, pixels=3000):
    reference = torch.rand(batch, pixels, generator=generator, dtype=torch.float64) * 256
    noise = 10 + 990 * torch.rand(batch, pixels, generator=generator, dtype=torch.float64)
    response = 40 + 120 * torch.sin(reference / 40)  # non-monotonic: one mean per bin
    misfit = torch.randn(batch, pixels, generator=generator, dtype=torch.float64) * (noise + tau2).sqrt()
    cells = hard_bin_index(reference, 64, RANGE)
    # Every pixel of a bin shares one mean, so the misfit variance is exactly tau^2.
    means = torch.stack([response[b].new_zeros(64).index_add(0, cells[b], response[b]) for b in range(batch)])
    counts = torch.stack([torch.bincount(cells[b], minlength=64) for b in range(batch)]).clamp_min(1)
    captured = (means / counts).gather(1, cells) + misfit
    return captured, cells, noise, torch.ones_like(captured, dtype=torch.bool)


@pytest.mark.parametrize("tau2", [50.0, 400.0, 3000.0])
def test_estimate_recovers_a_known_misfit_variance(tau2, generator):
    captured, cells, noise, valid = _aligned(tau2, generator)
    estimate = model_variance.estimate_model_variance(captured, cells, noise, valid, 64)
    assert ((estimate.mean() - tau2) / tau2).abs() < 0.1
    plain = model_variance.estimate_model_variance(captured, cells, noise, valid, 64, restricted=False)
    assert bool((plain < estimate).all())  # plain ML is biased low by the 64 fitted means


def test_estimate_is_the_maximum_of_the_likelihood(generator):
    captured, cells, noise, valid = _aligned(400.0, generator, batch=3)
    estimate = model_variance.estimate_model_variance(captured, cells, noise, valid, 64)
    around = estimate[None] * torch.tensor([0.98, 1.0, 1.02], dtype=torch.float64)[:, None]
    curve = model_variance.model_variance_log_likelihood(captured, cells, noise, valid, around, 64)
    assert bool((curve[1] >= curve[0]).all() and (curve[1] >= curve[2]).all())


def test_likelihood_matches_a_direct_loop(generator):
    captured, cells, noise, valid = _aligned(100.0, generator, batch=1, pixels=200)
    valid[0, :20] = False
    tau2 = torch.tensor([[7.0]], dtype=torch.float64)
    weight = 1 / (noise[0] + 7.0)
    log_det = residual = restricted = 0.0
    for label in range(64):
        members = valid[0] & (cells[0] == label)
        if not bool(members.any()):
            continue
        mean = (weight[members] * captured[0, members]).sum() / weight[members].sum()
        residual += (weight[members] * (captured[0, members] - mean) ** 2).sum()
        restricted += weight[members].sum().log()
    log_det = (noise[0][valid[0]] + 7.0).log().sum()
    expected = -0.5 * (log_det + residual + restricted)
    got = model_variance.model_variance_log_likelihood(captured, cells, noise, valid, tau2, 64)
    torch.testing.assert_close(got[0, 0], expected, rtol=1e-12, atol=1e-9)


def _images(generator, dtype):
    reference = torch.rand(2, 1, 30, 34, generator=generator, dtype=torch.float64) * 256
    variance = 50 + 900 * torch.rand(1, 1, 18, 20, generator=generator, dtype=torch.float64)
    # Noise of the stated variance plus a misfit of 15^2 that the stated variance leaves out.
    noise = torch.randn(2, 1, 18, 20, generator=generator, dtype=torch.float64) * (variance + 225).sqrt()
    captured = 200 - 0.7 * reference[..., 4:22, 3:23] + noise
    return captured.to(dtype), reference.to(dtype), variance.to(dtype)


def test_profile_with_one_plane_is_ecr_at_that_tau(generator, dtype):
    captured, reference, variance = _images(generator, dtype)
    surface, _ = model_variance.ecr_profile_surface(captured, reference, variance, bins=BINS, factors=(0.3,))
    spread = model_variance._spread_of(_check_inputs(captured, reference, None, None, RANGE, variance))
    for sample in range(2):
        expected = ecr_surface(
            captured[sample : sample + 1],
            reference[sample : sample + 1],
            variance,
            bins=BINS,
            model_variance=float(0.3 * spread[sample]),
        )
        tolerance = 1e-9 if dtype == torch.float64 else 2e-4
        torch.testing.assert_close(surface.score[sample], expected.score[0], rtol=tolerance, atol=tolerance)


def test_profile_is_the_best_plane_of_each_hypothesis(generator):
    # Two planes (no interpolation): n score = max_t l1_t - max_t l0_t - (K_occ - 1) / 2, where
    # l1_t = l0_t + n ECR_t + (K_occ - 1) / 2 and l0_t = -1/2 (sum log(s + tau_t^2) + sum w (v - weighted mean)^2).
    captured, reference, variance = _images(generator, torch.float64)
    factors = (1.0, 1 / 64)
    surface, _ = model_variance.ecr_profile_surface(captured, reference, variance, bins=BINS, factors=factors)
    spread = model_variance._spread_of(_check_inputs(captured, reference, None, None, RANGE, variance))
    count = 18 * 20
    for sample in range(2):
        nulls, alternatives = [], []
        for factor in factors:
            tau2 = float(factor * spread[sample])
            total = variance[0, 0] + tau2
            values = captured[sample, 0]
            mean = (values / total).sum() / (1 / total).sum()
            null = -0.5 * (total.log().sum() + ((values - mean) ** 2 / total).sum())
            ecr = ecr_surface(
                captured[sample : sample + 1], reference[sample : sample + 1], variance, bins=BINS, model_variance=tau2
            ).score[0]
            occupied = torch.tensor(
                [
                    hard_bin_index(reference[sample, 0, row : row + 18, col : col + 20], BINS, RANGE).unique().numel()
                    for row in range(13)
                    for col in range(15)
                ]
            ).view(13, 15)
            penalty = 0.5 * (occupied - 1)
            nulls.append(null)
            alternatives.append(null + count * ecr + penalty)
        expected = (torch.stack(alternatives).amax(0) - max(nulls) - penalty) / count
        torch.testing.assert_close(surface.score[sample], expected, rtol=1e-9, atol=1e-9)


def test_estimated_surface_is_ecr_at_its_estimate(generator, dtype):
    captured, reference, variance = _images(generator, dtype)
    truth = torch.tensor([[4, 3], [4, 3]])
    surface, tau2 = model_variance.ecr_estimated_surface(captured, reference, variance, bins=BINS, placements=truth)
    inputs = _check_inputs(captured, reference, None, None, RANGE, variance)
    direct = model_variance.estimate_at(inputs, truth, BINS, RANGE)
    torch.testing.assert_close(tau2, direct)
    for sample in range(2):
        expected = ecr_surface(
            captured[sample : sample + 1],
            reference[sample : sample + 1],
            variance,
            bins=BINS,
            model_variance=float(tau2[sample]),
        )
        torch.testing.assert_close(surface.score[sample], expected.score[0])
    # The true misfit: 15^2, plus the map's spread within a bin (0.7^2 32^2 / 12 = 42).
    assert bool(((tau2 > 100) & (tau2 < 800)).all()), tau2


def test_bin_variance_surface_matches_a_direct_likelihood(generator):
    captured, reference, variance = _images(generator, torch.float64)
    surface, pooled = model_variance.ecr_bin_variance_surface(captured, reference, variance, bins=BINS)
    inputs = _check_inputs(captured, reference, None, None, RANGE, variance)
    best = model_variance._argmax_placements(model_variance.first_pass(inputs, BINS, RANGE, "cheap"))
    cells = model_variance._sections_cells(inputs, best, BINS, RANGE)
    flat = captured.flatten(1)
    flat_variance = variance.flatten(1).expand_as(flat)
    for sample, row, col in [(0, 2, 5), (1, 4, 3), (0, 7, 0)]:
        present = torch.unique(hard_bin_index(reference[sample, 0], BINS, RANGE))
        per_bin = model_variance._per_bin_variances(
            flat[sample],
            cells[sample],
            flat_variance[sample],
            torch.ones_like(flat[sample], dtype=torch.bool),
            pooled[sample],
            present,
            32.0,
        )
        lookup = dict(zip(present.tolist(), per_bin.tolist(), strict=True))
        section = hard_bin_index(reference[sample, 0, row : row + 18, col : col + 20], BINS, RANGE).flatten()
        tau = torch.tensor([lookup[int(label)] for label in section], dtype=torch.float64)
        total = flat_variance[sample] + tau
        values = flat[sample] - flat[sample].mean()
        alternative = 0.0
        occupied = 0
        for label in section.unique().tolist():
            members = section == label
            weight = 1 / total[members]
            mean = (weight * values[members]).sum() / weight.sum()
            alternative += -0.5 * (total[members].log().sum() + (weight * (values[members] - mean) ** 2).sum())
            occupied += 1
        null_total = flat_variance[sample] + pooled[sample]
        null_mean = (values / null_total).sum() / (1 / null_total).sum()
        null = -0.5 * (null_total.log().sum() + ((values - null_mean) ** 2 / null_total).sum())
        expected = (alternative - null - 0.5 * (occupied - 1)) / 360
        torch.testing.assert_close(surface.score[sample, row, col], expected, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("tau2", [0.0, 50.0, 3000.0])
def test_scoring_reaches_the_grid_maximum(tau2, generator):
    captured, cells, noise, valid = _aligned(tau2, generator, batch=4)
    grid = model_variance.estimate_model_variance(captured, cells, noise, valid, 64)
    scored = model_variance.score_model_variance(captured, cells, noise, valid, 64, steps=12)
    torch.testing.assert_close(scored, grid, rtol=1e-4, atol=1e-2)
    fast = model_variance.score_model_variance(captured, cells, noise, valid, 64)  # the default 4 steps
    torch.testing.assert_close(fast, grid, rtol=1e-2, atol=0.5)


def test_gaussian_smooth_matches_scipy(generator):
    ndimage = pytest.importorskip("scipy.ndimage")
    planes = torch.rand(2, 17, 23, generator=generator, dtype=torch.float64)
    smoothed = model_variance._gaussian_smooth(planes, 2.5)
    for plane, got in zip(planes, smoothed, strict=True):
        expected = ndimage.gaussian_filter(plane.numpy(), 2.5, mode="constant", cval=0.0, truncate=3.2)
        torch.testing.assert_close(got, torch.from_numpy(expected), rtol=1e-12, atol=1e-12)


def _field_case(generator, dtype=torch.float64):
    """A captured image whose misfit variance is 3000 in a disc and 100 elsewhere, at placement (5, 7)."""
    reference = torch.rand(1, 1, 80, 90, generator=generator, dtype=torch.float64) * 256
    rows, cols = torch.meshgrid(torch.arange(64.0), torch.arange(70.0), indexing="ij")
    disc = (rows - 30) ** 2 + (cols - 40) ** 2 < 18**2
    misfit = torch.where(disc, 3000.0, 100.0).double()
    noise = (20 + 400 * rows / 63).double()[None, None]
    section = reference[..., 5:69, 7:77]
    captured = (
        60
        + 0.5 * section
        + torch.randn(section.shape, generator=generator, dtype=torch.float64) * (noise + misfit).sqrt()
    )
    return captured.to(dtype), reference.to(dtype), noise.to(dtype), misfit, disc


def test_local_field_recovers_a_known_misfit_map(generator):
    captured, reference, noise, misfit, disc = _field_case(generator)
    inputs = _check_inputs(captured, reference, None, None, (0.0, 256.0), noise)
    local, pooled = model_variance.local_model_variance(inputs, torch.tensor([[5, 7]]), 32, (0.0, 256.0))
    rows, cols = torch.meshgrid(torch.arange(64.0), torch.arange(70.0), indexing="ij")
    inner = (rows - 30) ** 2 + (cols - 40) ** 2 < 12**2
    outer = ~((rows - 30) ** 2 + (cols - 40) ** 2 < 24**2) & (rows > 5) & (rows < 58) & (cols > 5) & (cols < 64)
    # The map's spread within a bin (0.5^2 8^2 / 12 = 5) adds to the misfit.
    assert abs(float(local[0][inner].median()) / 3005 - 1) < 0.2
    assert abs(float(local[0][outer].median()) / 105 - 1) < 0.5
    assert float(misfit[disc].mean()) > float(pooled[0]) > float(misfit[~disc].mean())


def test_local_surface_is_ecr_with_the_field(generator, dtype):
    captured, reference, noise, _, _ = _field_case(generator, dtype)
    placements = torch.tensor([[5, 7]])
    surface, _ = model_variance.ecr_local_surface(captured, reference, noise, placements=placements)
    inputs = _check_inputs(captured, reference, None, None, (0.0, 256.0), noise)
    local, _ = model_variance.local_model_variance(inputs, placements, 32, (0.0, 256.0))
    expected = ecr_surface(captured, reference, noise + local[:, None], model_variance=0.0)
    torch.testing.assert_close(surface.score, expected.score)
    assert divmod(int(surface.score.flatten().argmax()), surface.score.shape[-1]) == (5, 7)


def test_separated_peaks_are_apart_and_ranked(generator):
    score = torch.rand(2, 9, 11, generator=generator)
    peaks = model_variance.separated_peaks(score, 4, radius=2)
    for sample in range(2):
        values = [float(score[sample, row, col]) for row, col in peaks[:, sample].tolist()]
        assert values == sorted(values, reverse=True) and values[0] == float(score[sample].max())
        for first in range(4):
            for second in range(first):
                assert (peaks[first, sample] - peaks[second, sample]).abs().max() > 2


def test_local_field_is_the_fisher_weighted_local_moment(generator):
    captured, reference, noise, _, _ = _field_case(generator)
    inputs = _check_inputs(captured, reference, None, None, (0.0, 256.0), noise)
    local, pooled = model_variance.local_model_variance(inputs, torch.tensor([[5, 7]]), 32, (0.0, 256.0))
    values = captured[0, 0]
    total = noise[0, 0].expand(64, 70) + pooled[0]
    cells = hard_bin_index(reference[0, 0, 5:69, 7:77], 32, (0.0, 256.0))
    residual = torch.empty_like(values)
    for label in cells.unique().tolist():
        members = cells == label
        weight = 1 / total[members]
        residual[members] = values[members] - (weight * values[members]).sum() / weight.sum()
    taps = torch.arange(-9, 10, dtype=torch.float64)
    kernel = torch.exp(-0.5 * (taps / 3) ** 2)
    kernel = kernel / kernel.sum()
    information = 1 / total.square()
    for row, col in [(0, 0), (30, 40), (63, 12), (17, 69)]:
        near_rows = torch.arange(max(0, row - 9), min(64, row + 10))
        near_cols = torch.arange(max(0, col - 9), min(70, col + 10))
        window = kernel[near_rows - row + 9][:, None] * kernel[near_cols - col + 9][None]
        info = information[near_rows][:, near_cols]
        excess = residual[near_rows][:, near_cols].square() - noise[0, 0][near_rows][:, near_cols]
        expected = ((window * info * excess).sum() / (window * info).sum()).clamp_min(0)
        torch.testing.assert_close(local[0, row, col], expected, rtol=1e-9, atol=1e-9)
