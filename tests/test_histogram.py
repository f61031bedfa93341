import math

import pytest
import torch
from torch.autograd import gradcheck

import enmi_torch.binning as binning_module
import enmi_torch.histogram as histogram_module
from enmi_torch.binning import bin_edges
from enmi_torch.functional import enmi, gaussian_log_prior, joint_histogram

RANGE = (0.0, 16.0)
BINS = 8


def _python_bin(value: float) -> int:
    return min(max(math.floor((value - RANGE[0]) / 2.0), 0), BINS - 1)


def _python_weights(value: float, variance: float, kernel: str) -> list[float]:
    """One pixel's bin weights from the definitions, with the math module only."""
    centres = [1.0 + 2.0 * index for index in range(BINS)]
    if kernel == "hard":
        return [1.0 if index == _python_bin(value) else 0.0 for index in range(BINS)]
    if kernel == "triangular":
        position = min(max((value - 1.0) / 2.0, 0.0), BINS - 1.0)
        return [max(0.0, 1.0 - abs(position - index)) for index in range(BINS)]
    if kernel == "mass":
        cdf = [0.5 * (1 + math.erf((2.0 * edge - value) / math.sqrt(2 * variance))) for edge in range(1, BINS)]
        cdf = [0.0, *cdf, 1.0]
        return [cdf[index + 1] - cdf[index] for index in range(BINS)]
    density = [math.exp(-((centre - value) ** 2) / (2 * variance)) for centre in centres]
    return [weight / sum(density) for weight in density]


def _python_joint_histogram(captured, reference, variance, valid, kernel):
    batch, pixels = len(captured), len(captured[0])
    counts = [[[0.0] * BINS for _ in range(BINS)] for _ in range(batch)]
    for sample in range(batch):
        for pixel in range(pixels):
            if valid is not None and not valid[sample][pixel]:
                continue
            weights = _python_weights(captured[sample][pixel], variance[sample][pixel], kernel)
            column = _python_bin(reference[sample][pixel])
            for row in range(BINS):
                counts[sample][row][column] += weights[row]
    return torch.tensor(counts, dtype=torch.float64)


@pytest.fixture
def pair(generator):
    reference = torch.rand(3, 1, 5, 7, generator=generator, dtype=torch.float64) * 18 - 1
    captured = reference + 2 * torch.randn(3, 1, 5, 7, generator=generator, dtype=torch.float64)
    variance = torch.rand(3, 1, 5, 7, generator=generator, dtype=torch.float64) * 6 + 0.05
    valid = torch.rand(3, 1, 5, 7, generator=generator) > 0.25
    return captured, reference, variance, valid


@pytest.mark.parametrize("kernel", ["hard", "triangular", "mass", "density"])
@pytest.mark.parametrize("masked", [False, True])
def test_vectorised_equals_python_loop(pair, kernel, masked):
    captured, reference, variance, valid = pair
    likelihood = kernel in ("mass", "density")
    counts = joint_histogram(
        captured,
        reference,
        bins=BINS,
        value_range=RANGE,
        captured_variance=variance if likelihood else None,
        valid_mask=valid if masked else None,
        kernel=kernel,
    )
    expected = _python_joint_histogram(
        captured.flatten(1).tolist(),
        reference.flatten(1).tolist(),
        variance.flatten(1).tolist(),
        valid.flatten(1).tolist() if masked else None,
        kernel,
    )
    torch.testing.assert_close(counts, expected, rtol=0, atol=1e-10)


def test_counts_sum_to_valid_pixels(pair, dtype):
    captured, reference, variance, valid = (
        tensor.to(dtype) if tensor.is_floating_point() else tensor for tensor in pair
    )
    counts = joint_histogram(
        captured, reference, bins=BINS, value_range=RANGE, captured_variance=variance, valid_mask=valid
    )
    assert counts.dtype == dtype
    torch.testing.assert_close(counts.sum((1, 2)), valid.flatten(1).sum(1).to(dtype))


@pytest.mark.parametrize("kernel", ["mass", "density"])
@pytest.mark.parametrize("with_prior", [False, True])
@pytest.mark.parametrize("clamped", [False, True])
def test_chunked_custom_function_equals_dense_autograd(pair, kernel, with_prior, clamped, monkeypatch):
    captured, reference, variance, valid = pair
    if clamped:  # two columns far below min_variance: clamped to it, so no gradient reaches their variance
        variance = variance.clone()
        variance[..., :2] = 1e-14  # min_variance(8, (0, 16)) is 4e-12
    log_prior = gaussian_log_prior(8.0, 4.0, BINS, RANGE, dtype=torch.float64) if with_prior else None
    cell_weights = torch.arange(BINS * BINS, dtype=torch.float64).reshape(BINS, BINS)
    monkeypatch.setattr(histogram_module, "_CHUNK_ELEMENTS", 40)  # several chunks for 35 pixels

    values, noise = captured.clone().requires_grad_(), variance.clone().requires_grad_()
    chunked = joint_histogram(
        values,
        reference,
        bins=BINS,
        value_range=RANGE,
        captured_variance=noise,
        valid_mask=valid,
        kernel=kernel,
        log_prior=log_prior,
    )
    (chunked * cell_weights).sum().backward()

    dense_values, dense_noise = captured.flatten(1).requires_grad_(), variance.flatten(1).requires_grad_()
    dense = histogram_module._dense_joint_histogram(
        dense_values,
        reference.flatten(1),
        dense_noise,
        valid.flatten(1).double(),
        None if log_prior is None else log_prior.reshape(1, 1, -1),
        BINS,
        RANGE,
        kernel,
        "hard",
    )
    (dense * cell_weights).sum().backward()
    torch.testing.assert_close(chunked, dense, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(values.grad.flatten(1), dense_values.grad, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(noise.grad.flatten(1), dense_noise.grad, rtol=1e-9, atol=1e-12)
    if clamped:
        assert (noise.grad[..., :2] == 0).all() and (noise.grad[..., 2:][valid[..., 2:]] != 0).any()


def test_clamped_exponent_leaves_the_chunked_gradients_unchanged(dtype, monkeypatch):
    generator = torch.Generator().manual_seed(5)
    reference = torch.rand(3, 1, 20, 24, generator=generator, dtype=dtype) * 256
    captured = (reference + 4 * torch.randn(3, 1, 20, 24, generator=generator, dtype=dtype)).requires_grad_()
    variance = (torch.rand(1, 1, 20, 24, generator=generator, dtype=dtype) * 30 + 0.5).requires_grad_()
    monkeypatch.setattr(histogram_module, "_CHUNK_ELEMENTS", 4096)  # several chunks
    # The case the clamp is for: most of the backward's exponents -z^2 / 2 lie below float32's denormal range.
    interior = bin_edges(32, (0.0, 256.0), dtype=dtype)[1:-1]
    exponent = -((interior - captured.detach().reshape(3, -1, 1)) ** 2) / (2 * variance.detach().reshape(1, -1, 1))
    assert (exponent < -87).double().mean() > 0.5

    def gradients():
        return torch.autograd.grad(enmi(captured, reference, variance).sum(), (captured, variance))

    clamped = gradients()
    monkeypatch.setattr(binning_module, "_EXP_FLOOR", -math.inf)
    unclamped = gradients()
    eps = torch.finfo(dtype).eps
    for got, want in zip(clamped, unclamped, strict=True):
        torch.testing.assert_close(got, want, rtol=4 * eps, atol=1e-30)


@pytest.mark.parametrize("kernel", ["mass", "density"])
def test_gradcheck_captured_and_variance(pair, kernel):
    captured, reference, variance, valid = pair
    inputs = (captured.clone().requires_grad_(), variance.clone().requires_grad_())

    def function(values, noise):
        return joint_histogram(
            values, reference, bins=BINS, value_range=RANGE, captured_variance=noise, valid_mask=valid, kernel=kernel
        )

    assert gradcheck(function, inputs)


@pytest.mark.parametrize("reference_kernel", ["triangular", "xu"])
def test_gradcheck_soft_reference(pair, reference_kernel):
    captured, reference, variance, _ = pair
    inputs = (captured.clone().requires_grad_(), reference.clone().requires_grad_())

    def function(values, map_values):
        return joint_histogram(
            values,
            map_values,
            bins=BINS,
            value_range=RANGE,
            captured_variance=variance,
            reference_kernel=reference_kernel,
        )

    assert gradcheck(function, inputs)


def test_variance_broadcast_forms_agree(pair):
    captured, reference, _, _ = pair
    variance_map = torch.linspace(0.5, 4.0, 35, dtype=torch.float64).reshape(5, 7)
    results = [
        joint_histogram(captured, reference, bins=BINS, value_range=RANGE, captured_variance=form)
        for form in (variance_map, variance_map[None, None], variance_map.expand(3, 1, 5, 7).clone())
    ]
    for result in results[1:]:
        torch.testing.assert_close(result, results[0])
    flat = joint_histogram(  # flat samples (B, 1, N), the map as (N,)
        captured.flatten(1)[:, None],
        reference.flatten(1)[:, None],
        bins=BINS,
        value_range=RANGE,
        captured_variance=variance_map.flatten(),
    )
    torch.testing.assert_close(flat, results[0])


def test_variance_gradient_sums_over_the_batch_for_a_shared_map(pair):
    captured, reference, _, _ = pair
    shared = torch.full((1, 1, 5, 7), 2.0, dtype=torch.float64, requires_grad=True)
    per_sample = shared.detach().expand(3, 1, 5, 7).clone().requires_grad_()
    for variance in (shared, per_sample):
        counts = joint_histogram(captured, reference, bins=BINS, value_range=RANGE, captured_variance=variance)
        counts.pow(2).sum().backward()
    torch.testing.assert_close(shared.grad, per_sample.grad.sum(0, keepdim=True))


def test_masked_pixels_may_hold_nan(pair):
    captured, reference, variance, valid = pair
    poisoned = captured.masked_fill(~valid, float("nan"))
    noisy_variance = variance.masked_fill(~valid, 0.0)
    values = poisoned.clone().requires_grad_()
    counts = joint_histogram(
        values, reference, bins=BINS, value_range=RANGE, captured_variance=noisy_variance, valid_mask=valid
    )
    clean = joint_histogram(
        captured, reference, bins=BINS, value_range=RANGE, captured_variance=variance, valid_mask=valid
    )
    torch.testing.assert_close(counts, clean)
    counts.pow(2).sum().backward()
    assert torch.isfinite(values.grad).all() and (values.grad[~valid] == 0).all()


def test_half_precision_is_accumulated_in_float32(pair):
    captured, reference, variance, _ = pair
    half = joint_histogram(
        captured.half(), reference.half(), bins=BINS, value_range=RANGE, captured_variance=variance.half()
    )
    single = joint_histogram(
        captured.half().float(),
        reference.half().float(),
        bins=BINS,
        value_range=RANGE,
        captured_variance=variance.half().float(),
    )
    assert half.dtype == torch.float16
    torch.testing.assert_close(half, single.half())


def test_streaming_counts_add_across_batches(pair):
    captured, reference, variance, valid = pair
    whole = joint_histogram(
        captured, reference, bins=BINS, value_range=RANGE, captured_variance=variance, valid_mask=valid
    )
    parts = [
        joint_histogram(
            captured[index : index + 1],
            reference[index : index + 1],
            bins=BINS,
            value_range=RANGE,
            captured_variance=variance[index : index + 1],
            valid_mask=valid[index : index + 1],
        )
        for index in range(3)
    ]
    torch.testing.assert_close(torch.cat(parts), whole)


@pytest.mark.parametrize("kernel", ["hard", "triangular", "xu", "mass", "density", "truncated"])
@pytest.mark.parametrize("reference_kernel", ["hard", "triangular", "xu"])
def test_masked_nan_pixels_in_either_image_are_left_out_for_every_kernel(kernel, reference_kernel, dtype, tolerance):
    generator = torch.Generator().manual_seed(8)
    captured = torch.rand(2, 1, 5, 7, generator=generator, dtype=dtype) * 256
    reference = torch.rand(2, 1, 5, 7, generator=generator, dtype=dtype) * 256
    mask = torch.zeros(2, 1, 5, 7, dtype=torch.bool)
    mask[..., 1:4, 2:6] = True
    variance = {"captured_variance": 30.0} if kernel in ("mass", "density", "truncated") else {}
    options = {"bins": 6, "kernel": kernel, "reference_kernel": reference_kernel, **variance}
    poisoned_reference = torch.where(mask, reference, torch.nan)
    poisoned_captured = torch.where(mask, captured, torch.inf)
    masked = joint_histogram(poisoned_captured, poisoned_reference, valid_mask=mask, **options)
    cropped = joint_histogram(captured[..., 1:4, 2:6], reference[..., 1:4, 2:6], **options)
    torch.testing.assert_close(masked, cropped, **tolerance)
    if kernel != "hard" or reference_kernel != "hard":
        captured_leaf = poisoned_captured.clone().requires_grad_()
        reference_leaf = poisoned_reference.clone().requires_grad_()
        joint_histogram(captured_leaf, reference_leaf, valid_mask=mask, **options).square().sum().backward()
        for leaf in (captured_leaf, reference_leaf):
            if leaf.grad is not None:
                assert torch.isfinite(leaf.grad).all() and (leaf.grad[~mask.expand_as(leaf)] == 0).all()


def test_pixel_weights_scale_each_valid_pixel_and_masked_pixels_stay_out(dtype, tolerance):
    generator = torch.Generator().manual_seed(11)
    captured = torch.rand(1, 1, 4, 6, generator=generator, dtype=dtype) * 256
    reference = torch.rand(1, 1, 4, 6, generator=generator, dtype=dtype) * 256
    weight = torch.rand(1, 1, 4, 6, generator=generator, dtype=dtype) + 0.5
    mask = torch.zeros(1, 1, 4, 6, dtype=torch.bool)
    mask[..., 1:3, 1:5] = True
    masked = joint_histogram(captured, reference, bins=5, valid_mask=mask, pixel_weight=weight)
    expected = torch.zeros(5, 5, dtype=torch.float64)
    for row in range(1, 3):
        for col in range(1, 5):
            i = min(int(captured[0, 0, row, col] // (256 / 5)), 4)
            j = min(int(reference[0, 0, row, col] // (256 / 5)), 4)
            expected[i, j] += weight[0, 0, row, col].item()
    torch.testing.assert_close(masked[0].double(), expected, **tolerance)
    with pytest.raises(ValueError, match="pixel_weight must be >= 0 where valid"):
        joint_histogram(captured, reference, bins=5, pixel_weight=-weight)
    # A weight of 0 is allowed everywhere: it leaves the pixel out, as a mask does.
    zeroed = torch.where(mask, weight, 0.0)
    torch.testing.assert_close(joint_histogram(captured, reference, bins=5, pixel_weight=zeroed), masked, **tolerance)
