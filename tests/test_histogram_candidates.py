"""Candidate references (``reference`` of shape ``(C, *captured.shape)``) and the pixel-wise hard entropies."""

import importlib

import pytest
import torch
from torch.autograd import gradcheck

import enmi_torch.histogram as histogram_module
from enmi_torch.functional import enmi, entropies, gaussian_log_prior, joint_histogram, nmi, nmi_from_joint_histogram
from enmi_torch.histogram import hard_entropies

RANGE = (0.0, 16.0)
BINS = 8
KERNELS = [
    ("hard", "hard", False),
    ("triangular", "hard", False),
    ("xu", "triangular", False),
    ("mass", "hard", False),
    ("density", "hard", False),
    ("mass", "hard", True),
    ("mass", "xu", False),
    ("density", "triangular", True),
]


@pytest.fixture
def images(generator):
    captured = torch.rand(3, 1, 5, 7, generator=generator, dtype=torch.float64) * 18 - 1
    candidates = torch.rand(4, 3, 1, 5, 7, generator=generator, dtype=torch.float64) * 18 - 1
    candidates[0] = captured + 0.5 * torch.randn(3, 1, 5, 7, generator=generator, dtype=torch.float64)
    variance = torch.rand(3, 1, 5, 7, generator=generator, dtype=torch.float64) * 6 + 0.05
    valid = torch.rand(3, 1, 5, 7, generator=generator) > 0.25
    return captured, candidates, variance, valid


def _options(kernel, reference_kernel, with_prior, variance, dtype):
    likelihood = kernel in ("mass", "density")
    return {
        "bins": BINS,
        "value_range": RANGE,
        "kernel": kernel,
        "reference_kernel": reference_kernel,
        "captured_variance": variance.to(dtype) if likelihood else None,
        "log_prior": gaussian_log_prior(8.0, 4.0, BINS, RANGE, dtype=dtype) if with_prior else None,
    }


@pytest.mark.parametrize(("kernel", "reference_kernel", "with_prior"), KERNELS)
@pytest.mark.parametrize("masked", [False, True])
def test_candidates_equal_one_call_per_candidate(
    images, kernel, reference_kernel, with_prior, masked, dtype, tolerance
):
    captured, candidates, variance, valid = (
        tensor.to(dtype) if tensor.is_floating_point() else tensor for tensor in images
    )
    options = _options(kernel, reference_kernel, with_prior, variance, dtype)
    mask = valid if masked else None
    together = joint_histogram(captured, candidates, valid_mask=mask, **options)
    assert together.shape == (4, 3, BINS, BINS) and together.dtype == dtype
    for index, candidate in enumerate(candidates):
        alone = joint_histogram(captured, candidate, valid_mask=mask, **options)
        torch.testing.assert_close(together[index], alone, **tolerance)


@pytest.mark.parametrize("kernel", ["mass", "density"])
def test_candidate_gradients_sum_the_per_candidate_gradients(images, kernel, monkeypatch):
    captured, candidates, variance, valid = images
    monkeypatch.setattr(histogram_module, "_CHUNK_ELEMENTS", 40)  # several chunks of the custom function
    cell_weights = torch.randn(4, 1, BINS, BINS, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    values, noise = captured.clone().requires_grad_(), variance.clone().requires_grad_()
    counts = joint_histogram(
        values, candidates, bins=BINS, value_range=RANGE, captured_variance=noise, valid_mask=valid, kernel=kernel
    )
    (counts * cell_weights).sum().backward()
    expected_values, expected_noise = torch.zeros_like(captured), torch.zeros_like(variance)
    for index, candidate in enumerate(candidates):
        single_values, single_noise = captured.clone().requires_grad_(), variance.clone().requires_grad_()
        single = joint_histogram(
            single_values,
            candidate,
            bins=BINS,
            value_range=RANGE,
            captured_variance=single_noise,
            valid_mask=valid,
            kernel=kernel,
        )
        (single * cell_weights[index]).sum().backward()
        expected_values += single_values.grad
        expected_noise += single_noise.grad
    torch.testing.assert_close(values.grad, expected_values, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(noise.grad, expected_noise, rtol=1e-9, atol=1e-12)


def test_gradcheck_enmi_with_candidates(images):
    captured, candidates, variance, valid = images
    inputs = (captured[:2].clone().requires_grad_(), variance[:2].clone().requires_grad_())

    def score(values, noise):
        return enmi(values, candidates[:3, :2], noise, bins=BINS, value_range=RANGE, valid_mask=valid[:2])

    assert gradcheck(score, inputs, eps=1e-6, atol=1e-6)


def test_nmi_and_enmi_with_candidates_return_one_score_per_candidate(images):
    captured, candidates, variance, _ = images
    hard = nmi(captured, candidates, bins=BINS, value_range=RANGE, kernel="hard")
    soft = enmi(captured, candidates, variance, bins=BINS, value_range=RANGE)
    assert hard.shape == soft.shape == (4, 3)
    for index, candidate in enumerate(candidates):
        torch.testing.assert_close(hard[index], nmi(captured, candidate, bins=BINS, value_range=RANGE, kernel="hard"))
        torch.testing.assert_close(soft[index], enmi(captured, candidate, variance, bins=BINS, value_range=RANGE))
    # The first candidate is the captured image plus small noise: it scores best.
    assert bool((hard.argmax(0) == 0).all()) and bool((soft.argmax(0) == 0).all())
    counts = joint_histogram(captured, candidates, bins=BINS, value_range=RANGE)
    torch.testing.assert_close(nmi_from_joint_histogram(counts), hard)


@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("with_candidates", [False, True])
def test_hard_entropies_equal_the_entropies_of_the_hard_histogram(images, masked, with_candidates, dtype):
    captured, candidates, _, valid = images
    reference = candidates if with_candidates else candidates[1]
    mask = valid if masked else None
    # Values on bin edges and outside the range, and a sample in one cell, exercise the clipping and H = 0.
    captured, reference = captured.clone(), reference.clone()
    captured[0, 0, 0, :3] = torch.tensor([0.0, 2.0, 16.0])
    captured[2] = 5.0
    reference[..., 2, :, :, :] = 5.0
    captured, reference = captured.to(dtype), reference.to(dtype)
    counts = joint_histogram(captured, reference, bins=BINS, value_range=RANGE, valid_mask=mask)
    expected = entropies(counts.to(torch.float64))
    actual = hard_entropies(captured, reference, bins=BINS, value_range=RANGE, valid_mask=mask)
    atol = 1e-12 if dtype == torch.float64 else 2e-6
    for got, want in zip(actual, expected, strict=True):
        assert got.dtype == dtype and got.shape == want.shape
        torch.testing.assert_close(got.double(), want, rtol=0, atol=atol)
    assert float(actual[2][..., 2].abs().max()) == 0.0  # one cell: exactly zero joint entropy
    torch.testing.assert_close(
        nmi(captured, reference, bins=BINS, value_range=RANGE, valid_mask=mask, kernel="hard").double(),
        nmi_from_joint_histogram(counts.double()),
        rtol=0,
        atol=atol,
    )


def test_masked_pixels_may_hold_nan_in_the_hard_entropies(images):
    captured, candidates, _, valid = images
    poisoned = captured.masked_fill(~valid, float("nan"))
    reference = candidates.masked_fill(~valid, float("inf"))
    clean = hard_entropies(captured, candidates, bins=BINS, value_range=RANGE, valid_mask=valid)
    poisoned_entropies = hard_entropies(poisoned, reference, bins=BINS, value_range=RANGE, valid_mask=valid)
    for got, want in zip(poisoned_entropies, clean, strict=True):
        torch.testing.assert_close(got, want)


@pytest.mark.parametrize(
    ("reference", "message"),
    [
        (
            torch.zeros(2, 4, 1, 5, 7),
            r"reference must have the shape of captured \(3, 1, 5, 7\) or \(C, \*that shape\)",
        ),
        (torch.zeros(0, 3, 1, 5, 7), "reference must hold at least one candidate"),
        (torch.zeros(2, 2, 3, 1, 5, 7), "reference must have the shape of captured"),
    ],
)
def test_invalid_candidate_shapes_raise_clear_errors(images, reference, message):
    captured = images[0]
    for call in (
        lambda: joint_histogram(captured, reference.double()),
        lambda: hard_entropies(captured, reference.double()),
        lambda: enmi(captured, reference.double(), 1.0),
    ):
        with pytest.raises(ValueError, match=message):
            call()
    with pytest.raises(ValueError, match=r"counts must have shape \(B, K, K\) or \(\.\.\., B, K, K\)"):
        nmi_from_joint_histogram(torch.ones(4, 4))


@pytest.mark.parametrize(("bins", "pixel_wise"), [(32, True), (8, False)])
def test_nmi_reads_hard_entropies_at_the_pixels_only_for_small_images(images, bins, pixel_wise, monkeypatch):
    information_module = importlib.import_module("enmi_torch.scores.nmi")  # enmi_torch.scores.nmi is the function

    captured, candidates, _, valid = images
    calls = []

    def spy(*args, **kwargs):
        calls.append(1)
        return hard_entropies(*args, **kwargs)

    monkeypatch.setattr(information_module, "hard_entropies", spy)
    score = nmi(captured, candidates, bins=bins, value_range=RANGE, valid_mask=valid, kernel="hard")
    assert bool(calls) == pixel_wise  # 35 pixels: fewer than 32^2 / 4, more than 8^2 / 4
    counts = joint_histogram(captured, candidates, bins=bins, value_range=RANGE, valid_mask=valid)
    torch.testing.assert_close(score, nmi_from_joint_histogram(counts), rtol=0, atol=1e-12)


def test_hard_entropies_by_sorted_runs_equal_the_counting_table(images, monkeypatch):
    # Small images and 32 bins: the table path by default; with no table allowed, the sorted-run path.
    captured, candidates, _, mask = images
    table = hard_entropies(captured, candidates, bins=BINS, value_range=RANGE, valid_mask=mask)
    monkeypatch.setattr(histogram_module, "_TABLE_CELLS", 0)
    monkeypatch.setattr(histogram_module, "_cell_weights", _sorted_only(histogram_module._cell_weights))
    runs = hard_entropies(captured, candidates, bins=BINS, value_range=RANGE, valid_mask=mask)
    for expected, actual in zip(table, runs, strict=True):
        torch.testing.assert_close(actual, expected, rtol=1e-12, atol=1e-12)


def _sorted_only(cell_weights):
    """``_cell_weights`` forced onto its sorted-run branch (as for large images with many bins)."""

    def forced(cells, cell_count, weight):
        return cell_weights(cells, max(cell_count, 16 * cells.shape[-1] + 1), weight)

    return forced
