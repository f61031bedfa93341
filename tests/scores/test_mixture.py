import itertools
import math

import mpmath
import numpy as np
import pytest
import torch

from enmi_torch import Mixture
from enmi_torch.binning import _log_bin_masses, _LowerLogNdtr, likelihood_weights, truncated_likelihood_weights
from enmi_torch.functional import mixture_information, mixture_surface
from enmi_torch.losses import MixtureLoss
from enmi_torch.placement.peaks import rescore_peaks
from enmi_torch.scores import direct_surface
from enmi_torch.scores.ecr import ecr_surface
from enmi_torch.scores.mixture import _mixture_log_likelihoods
from enmi_torch.utils.budget import MemoryBudgetError


def _numpy_weights(values, variance, bins, value_range):
    """Independent reference: Gaussian bin masses from math.erf, truncated to the range and normalised."""
    edges = np.linspace(*value_range, bins + 1)
    rows = []
    for value, var in zip(np.ravel(values), np.ravel(variance), strict=True):
        scale = math.sqrt(2 * var)
        cdf = np.array([math.erf((edge - value) / scale) for edge in edges])
        masses = np.diff(cdf)
        rows.append(masses / masses.sum())
    return np.array(rows)


def _numpy_mixture(captured, reference, variance, bins, value_range, valid, em_steps=0):
    """Independent reference: the soft joint histogram and both mixture models, one pixel at a time, float64."""
    keep = np.asarray(valid, bool).ravel()
    values = np.asarray(captured, np.float64).ravel()[keep]
    likelihoods = _numpy_weights(values, np.asarray(variance, np.float64).ravel()[keep], bins, value_range)
    width = (value_range[1] - value_range[0]) / bins
    reference_bins = np.clip(
        np.floor((np.asarray(reference, np.float64).ravel()[keep] - value_range[0]) / width), 0, bins - 1
    )
    reference_bins = reference_bins.astype(int)
    pixels = len(values)

    def conditional_from(joint):
        totals = joint.sum(0, keepdims=True)
        return np.divide(joint, totals, out=np.zeros_like(joint), where=totals > 0)

    joint = np.zeros((bins, bins))
    for likelihood, column in zip(likelihoods, reference_bins, strict=True):
        joint[:, column] += likelihood
    conditional, marginal = conditional_from(joint), joint.sum(1) / pixels
    for _ in range(em_steps):
        joint, new_marginal = np.zeros((bins, bins)), np.zeros(bins)
        for likelihood, column in zip(likelihoods, reference_bins, strict=True):
            responsibility = likelihood * conditional[:, column]
            joint[:, column] += responsibility / responsibility.sum()
            responsibility = likelihood * marginal
            new_marginal += responsibility / responsibility.sum()
        conditional, marginal = conditional_from(joint), new_marginal / pixels
    total = 0.0
    for likelihood, column in zip(likelihoods, reference_bins, strict=True):
        total += math.log(likelihood @ conditional[:, column]) - math.log(likelihood @ marginal)
    return total / pixels


def _numpy_hard_mutual_information(captured, reference, bins, value_range):
    counts, _, _ = np.histogram2d(np.ravel(captured), np.ravel(reference), bins=bins, range=[value_range] * 2)
    joint = counts / counts.sum()
    outer = joint.sum(1, keepdims=True) * joint.sum(0, keepdims=True)
    nonzero = joint > 0
    return float(np.sum(joint[nonzero] * np.log(joint[nonzero] / outer[nonzero])))


def _case(dtype, shape=(2, 1, 7, 5), seed=0):
    generator = torch.Generator().manual_seed(seed)
    reference = torch.rand(shape, generator=generator, dtype=torch.float64) * 256
    # Non-monotonic response, noise of per-pixel variance, some values beyond the range.
    captured = 300 * (reference / 256 - 0.4).abs() + torch.randn(shape, generator=generator, dtype=torch.float64) * 20
    variance = torch.rand(shape, generator=generator, dtype=torch.float64) * 900 + 4
    valid = torch.rand(shape, generator=generator) > 0.2
    return captured.to(dtype), reference.to(dtype), variance.to(dtype), valid


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
    # Each form: erf (across the value or within a standard deviation), log_ndtr (beyond); values inside the
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
    # Across the value and within a standard deviation (erf), beyond (log_ndtr), below and above the range.
    values = torch.tensor([3.3, 5.0, -2.5, 12.0, -30.0, 50.0], dtype=torch.float64, requires_grad=True)
    variance = torch.tensor([1.0, 0.2, 2.0, 1.5, 4.0, 9.0], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v, s: _log_bin_masses(v, s, 4, (0.0, 8.0)), (values, variance))


@pytest.mark.parametrize("em_steps", [0, 2])
def test_mixture_equals_numpy_loop(dtype, tolerance, em_steps):
    captured, reference, variance, valid = _case(dtype)
    bins, value_range = 6, (0.0, 256.0)
    result = mixture_information(captured, reference, variance, bins=bins, em_steps=em_steps, valid_mask=valid)
    expected = [
        _numpy_mixture(captured[b, 0], reference[b, 0], variance[b, 0], bins, value_range, valid[b, 0], em_steps)
        for b in range(captured.shape[0])
    ]
    assert result.dtype == dtype
    torch.testing.assert_close(result, torch.tensor(expected, dtype=dtype), **tolerance)


def test_mixture_candidates_equal_one_call_each_and_roles_are_not_symmetric(dtype, tolerance):
    captured, reference, variance, valid = _case(dtype)
    candidates = torch.stack([reference, reference.flip(-1), captured])
    together = mixture_information(captured, candidates, variance, bins=5, em_steps=1, valid_mask=valid)
    assert together.shape == (3, 2)
    for index in range(3):
        alone = mixture_information(captured, candidates[index], variance, bins=5, em_steps=1, valid_mask=valid)
        torch.testing.assert_close(together[index], alone, **tolerance)
    swapped = mixture_information(reference, captured, variance, bins=5, em_steps=1, valid_mask=valid)
    assert not torch.allclose(swapped, together[0], rtol=1e-2)


@pytest.mark.parametrize("em_steps", [0, 3])
def test_noiseless_limit_is_plugin_mutual_information_of_the_hard_histogram(em_steps):
    captured, reference, _, _ = _case(torch.float64, shape=(1, 1, 13, 9), seed=1)
    bins, value_range = 7, (0.0, 256.0)
    clipped = captured.clamp(0, 255.999)  # numpy's histogram drops values outside, the hard bins clip them
    result = mixture_information(captured, reference, 1e-12, bins=bins, em_steps=em_steps)
    expected = _numpy_hard_mutual_information(clipped.numpy(), reference.numpy(), bins, value_range)
    assert math.isclose(result.item(), expected, rel_tol=1e-12)


def test_a_pixel_with_a_flat_likelihood_adds_nothing_of_its_own():
    captured, reference, _, _ = _case(torch.float64, shape=(1, 1, 12, 12))
    bins, value_range = 4, (0.0, 256.0)
    base = mixture_information(captured, reference, 1e-12, bins=bins) * 144
    # One more pixel over the first pixel's reference bin, with an enormous noise variance and a wild value.
    variance = torch.cat([torch.full((1, 144), 1e-12, dtype=torch.float64), torch.tensor([[1e16]])], 1)
    grown = (
        mixture_information(
            torch.cat([captured.flatten(1), torch.tensor([[1e4]], dtype=torch.float64)], 1)[:, None],  # (B, 1, N)
            torch.cat([reference.flatten(1), reference.flatten(1)[:, :1]], 1)[:, None],
            variance,
            bins=bins,
        )
        * 145
    )
    # Its own term is log(1/K) - log(1/K) = 0: the change is only the 1/K per bin it adds to its column's histogram,
    # diluting the other pixels' p(i | j) of that column and p(i).
    clipped = captured.clamp(0, 255.999).flatten().numpy()
    counts, _, _ = np.histogram2d(clipped, reference.flatten().numpy(), bins=bins, range=[value_range] * 2)
    column = int(reference.flatten()[0] // (256 / bins))
    in_column, column_total = counts[:, column], counts[:, column].sum()
    rows, total = counts.sum(1), counts.sum()
    occupied, row_occupied = in_column > 0, rows > 0
    conditional = np.sum(
        in_column[occupied]
        * (np.log((in_column[occupied] + 1 / bins) / (column_total + 1)) - np.log(in_column[occupied] / column_total))
    )
    marginal = np.sum(
        rows[row_occupied]
        * (np.log((rows[row_occupied] + 1 / bins) / (total + 1)) - np.log(rows[row_occupied] / total))
    )
    assert math.isclose((grown - base).item(), conditional - marginal, rel_tol=1e-6, abs_tol=1e-9)
    assert abs(conditional - marginal) > 0.05  # the dilution is there, and it is what the test measures


def test_mixture_masked_equals_cropped_and_masked_pixels_may_hold_nan(dtype, tolerance):
    captured, reference, variance, _ = _case(dtype, shape=(1, 1, 6, 8))
    mask = torch.zeros(1, 1, 6, 8, dtype=torch.bool)
    mask[..., 1:5, 2:7] = True
    poisoned = torch.where(mask, captured, torch.nan)
    masked = mixture_information(poisoned, reference, variance, bins=5, em_steps=2, valid_mask=mask)
    cropped = mixture_information(
        captured[..., 1:5, 2:7], reference[..., 1:5, 2:7], variance[..., 1:5, 2:7], bins=5, em_steps=2
    )
    torch.testing.assert_close(masked, cropped, **tolerance)


@pytest.mark.parametrize("em_steps", [0, 1])
def test_mixture_gradcheck_in_captured_and_variance(em_steps):
    captured, reference, variance, valid = _case(torch.float64, shape=(2, 1, 4, 3))
    captured.requires_grad_()
    variance.requires_grad_()

    def score(captured, variance):
        return mixture_information(captured, reference, variance, bins=4, em_steps=em_steps, valid_mask=valid)

    assert torch.autograd.gradcheck(score, (captured, variance))
    score(captured, variance).sum().backward()
    assert (captured.grad[~valid] == 0).all() and (variance.grad[~valid] == 0).all()


def test_em_steps_never_decrease_either_model_log_likelihood():
    captured, reference, variance, valid = _case(torch.float64, shape=(2, 1, 9, 7), seed=2)
    weights = truncated_likelihood_weights(captured.flatten(1), variance.flatten(1), 6, (0.0, 256.0))
    reference_bins = (reference.flatten(1) / (256 / 6)).floor().long().clamp(0, 5)[None]
    history = [
        _mixture_log_likelihoods(weights, reference_bins, valid.flatten(1).double(), 6, steps) for steps in range(6)
    ]
    for before, after in itertools.pairwise(history):
        assert (after[0] >= before[0] - 1e-9).all() and (after[1] >= before[1] - 1e-9).all()
    assert (history[-1][0] > history[0][0] + 1e-3).all()


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"variance": None}, ValueError, "variance must be"),
        ({"em_steps": -1}, ValueError, "em_steps must be an int >= 0, got -1"),
        ({"em_steps": 1.5}, TypeError, "em_steps must be an int >= 0"),
        ({"variance": -1.0}, ValueError, "variance"),
        ({"bins": 1}, ValueError, "bins"),
        ({"value_range": (5.0, 5.0)}, ValueError, "value_range"),
        ({"reference": torch.zeros(2, 1, 5, 7)}, ValueError, "reference must have the shape of captured"),
    ],
)
def test_mixture_refuses_bad_arguments(kwargs, error, message):
    captured, reference, variance, _ = _case(torch.float64)
    arguments = {"variance": variance, "reference": reference, **kwargs}
    variance, reference = arguments.pop("variance"), arguments.pop("reference")
    with pytest.raises(error, match=message):
        mixture_information(captured, reference, variance, **arguments)


def _surface_case(seed, batch=1, windows=1, masks=False):
    generator = torch.Generator().manual_seed(seed)
    window = torch.rand(windows, 1, 13, 11, generator=generator, dtype=torch.float64) * 256
    window = torch.nn.functional.avg_pool2d(window, 3, 1, 1, count_include_pad=False) * 2 - 128  # some texture
    tops, lefts = [4, 2], [4, 1]
    local = torch.cat(
        [
            window[min(b, windows - 1) : min(b, windows - 1) + 1, :, tops[b] : tops[b] + 7, lefts[b] : lefts[b] + 6]
            for b in range(batch)
        ]
    )
    local = 280 * (local / 256 - 0.3).abs() + 12 * torch.randn(local.shape, generator=generator, dtype=torch.float64)
    variance = torch.rand(batch, 1, 7, 6, generator=generator, dtype=torch.float64) * 300 + 50
    options = {}
    if masks:
        options["captured_mask"] = torch.rand(batch, 1, 7, 6, generator=generator) > 0.15
        reference_mask = torch.ones(windows, 1, 13, 11, dtype=torch.bool)
        reference_mask[..., :3, :4] = False
        options["reference_mask"] = reference_mask
    return local, window, variance, options


@pytest.mark.parametrize(
    ("seed", "batch", "windows", "masks", "em_steps"),
    [(0, 1, 1, False, 0), (1, 2, 1, True, 0), (2, 2, 2, True, 1), (3, 1, 1, True, 2)],
)
def test_two_stage_surface_equals_direct_where_rescored_and_has_its_argmax(seed, batch, windows, masks, em_steps):
    local, window, variance, options = _surface_case(seed, batch, windows, masks)
    fast = mixture_surface(local, window, variance, bins=8, em_steps=em_steps, candidates=2, **options)
    slow = direct_surface(Mixture(bins=8, em_steps=em_steps), local, window, variance, **options)
    rescored = fast.scored  # the surface says which placements it scored
    assert torch.equal(rescored, torch.isfinite(fast.score)) and slow.scored is None
    assert fast.score.shape == slow.score.shape == (batch, 7, 6)
    assert rescored.sum() >= 9 * batch and (~rescored).any()
    torch.testing.assert_close(fast.score[rescored], slow.score[rescored], rtol=1e-9, atol=1e-9)
    assert torch.equal(fast.score.flatten(1).argmax(1), slow.score.flatten(1).argmax(1))
    torch.testing.assert_close(fast.overlap, slow.overlap)
    cheap = ecr_surface(local, window, variance, bins=8, **options)
    torch.testing.assert_close(fast.overlap, cheap.overlap)


def test_two_stage_surface_in_float32_agrees_with_float64():
    local, window, variance, options = _surface_case(1, 2, 1, True)
    double = mixture_surface(local, window, variance, bins=8, **options)
    single = mixture_surface(local.float(), window.float(), variance.float(), bins=8, **options)
    assert single.score.dtype == torch.float32
    rescored = torch.isfinite(double.score) & torch.isfinite(single.score)
    torch.testing.assert_close(single.score[rescored], double.score[rescored].float(), rtol=1e-4, atol=1e-5)


def test_mixture_runs_on_the_device(device):
    local, window, variance, options = _surface_case(2, 2, 2, True)
    expected = mixture_surface(local, window, variance, bins=8, em_steps=1, **options)
    moved = mixture_surface(
        local.to(device),
        window.to(device),
        variance.to(device),
        bins=8,
        em_steps=1,
        **{name: mask.to(device) for name, mask in options.items()},
    )
    torch.testing.assert_close(moved.score.cpu(), expected.score)
    captured, reference, variance, valid = _case(torch.float64)
    captured.requires_grad_()
    score = mixture_information(
        captured.to(device), reference.to(device), variance.to(device), bins=5, valid_mask=valid.to(device)
    )
    score.sum().backward()
    assert score.device.type == device.type and torch.isfinite(captured.grad).all()


def _peaks_case():
    """A cheap surface with 20 isolated peaks of decreasing height on a flat floor."""
    cheap = torch.zeros(12, 15, dtype=torch.float64)
    peaks = [(row, col) for row in range(1, 12, 3) for col in range(1, 15, 3)]
    for rank, (row, col) in enumerate(peaks):
        cheap[row, col] = 100.0 - rank
    return cheap, peaks


def _exact_favouring(peaks, target=None):
    """Exact scores: 1000 at ``target``, else the cheap rank of the peak whose 3 x 3 block holds the placement."""

    def exact(placements):
        rows, cols = placements.unbind(-1)
        ranks = torch.tensor([peaks.index((row // 3 * 3 + 1, col // 3 * 3 + 1)) for row, col in placements.tolist()])
        hit = (rows == target[0]) & (cols == target[1]) if target else torch.zeros_like(rows, dtype=torch.bool)
        return torch.where(hit, 1000.0, ranks.double())

    return exact


@pytest.mark.parametrize(
    ("best_rank", "expected_peaks"), [(0, 8), (3, 8), (4, 16), (7, 16), (8, 20), (12, 20), (19, 20)]
)
def test_rescoring_doubles_while_the_exact_best_comes_from_the_lower_half(best_rank, expected_peaks):
    cheap, peaks = _peaks_case()
    best = peaks[best_rank]
    # Until the target's peak is rescored, the exact best sits by the lowest-ranked peak rescored (the lower half).
    exact = _exact_favouring(peaks, (best[0], best[1] + 1))

    score = rescore_peaks(cheap, exact, 8, 64)
    rescored_peaks = sum(bool(torch.isfinite(score[row, col])) for row, col in peaks)
    assert rescored_peaks == expected_peaks
    # Each rescored peak brings its 8 neighbours (none shared here, none outside).
    assert int(torch.isfinite(score).sum()) == 9 * expected_peaks
    assert divmod(int(score.argmax()), 15) == (best[0], best[1] + 1)


def test_rescoring_takes_separated_peaks_not_the_shoulders_of_one():
    cheap = torch.zeros(9, 10, dtype=torch.float64)
    cheap[5, 5], cheap[5, 6], cheap[4, 5] = 10.0, 9.9, 9.8  # one broad peak
    cheap[1, 1] = 5.0  # a second, lower one

    def exact(placements):
        return -placements.sum(-1).double()

    score = rescore_peaks(cheap, exact, 2, 2)
    assert torch.isfinite(score[1, 1]) and torch.isfinite(score[5, 5])
    assert int(torch.isfinite(score).sum()) == 18


def test_rescoring_stops_at_max_candidates():
    cheap, peaks = _peaks_case()

    score = rescore_peaks(cheap, _exact_favouring(peaks), 2, 5)  # always best by the lowest-ranked peak
    assert sum(bool(torch.isfinite(score[row, col])) for row, col in peaks) == 5


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"variance": None}, ValueError, "variance must be"),
        ({"candidates": 0}, ValueError, "candidates must be an int >= 1"),
        ({"max_candidates": 4, "candidates": 8}, ValueError, r"max_candidates must be >= candidates \(8\), got 4"),
        ({"em_steps": -2}, ValueError, "em_steps must be an int >= 0"),
        (
            {"reference": torch.zeros(1, 1, 5, 5, dtype=torch.float64)},
            ValueError,
            "captured must not be larger than reference",
        ),
    ],
)
def test_mixture_surface_refuses_bad_arguments(kwargs, error, message):
    local, window, variance, _ = _surface_case(0)
    arguments = {"variance": variance, "reference": window, **kwargs}
    variance, window = arguments.pop("variance"), arguments.pop("reference")
    with pytest.raises(error, match=message):
        mixture_surface(local, window, variance, **arguments)


@pytest.mark.parametrize("variance", [1e-5, 1e-6, 1e-9])
def test_float32_gradients_stay_finite_at_tiny_variances_also_through_the_loss(variance):
    generator = torch.Generator().manual_seed(0)
    reference = torch.rand(2, 1, 8, 8, generator=generator) * 256
    captured = (reference + 0.3).requires_grad_()
    noise = torch.full_like(reference, variance).requires_grad_()
    mixture_information(captured, reference, noise).sum().backward()
    assert torch.isfinite(captured.grad).all() and torch.isfinite(noise.grad).all()
    captured.grad = None
    MixtureLoss()(captured, reference, variance=variance).backward()
    assert torch.isfinite(captured.grad).all()


def test_lower_log_ndtr_has_the_inverse_mills_ratio_for_its_derivative():
    standardized = torch.tensor([0.0, -1.0, -10.0, -1e3, -1e4, -1e6, -1e10], dtype=torch.float64, requires_grad=True)
    _LowerLogNdtr.apply(standardized).sum().backward()
    # phi(z) / Phi(z) -> -z - 1 / z (1 + O(z^-2)) far in the lower tail; exact values below 10.
    expected = [math.sqrt(2 / math.pi), 1.525135276160981, 10.098093233962512, 1e3 + 1e-3, 1e4 + 1e-4, 1e6, 1e10]
    assert standardized.grad.tolist() == pytest.approx(expected, rel=1e-9)
    assert torch.autograd.gradcheck(_LowerLogNdtr.apply, (standardized.detach()[:4].clone().requires_grad_(),))


def test_mixture_refuses_bins_over_the_memory_budget_before_allocating():
    image = torch.rand(1, 1, 8, 8) * 256
    with pytest.raises(MemoryBudgetError, match=r"bins=100000 needs about .* GiB for the joint histograms"):
        mixture_information(image, image, 1.0, bins=100_000)
    with pytest.raises(MemoryBudgetError, match=r"bins=100000"):
        mixture_surface(image[..., :4, :4], image, 1.0, bins=100_000)
