import itertools

import numpy as np
import pytest
import torch
from kornia.losses import normalized_mutual_information_loss_2d
from skimage.metrics import normalized_mutual_information
from torch.autograd import gradcheck

from enmi_torch.functional import enmi, entropies, joint_histogram, nmi, nmi_from_joint_histogram
from enmi_torch.utils.checks import value_checks

EDGES = np.linspace(0, 256, 33)


def _skimage_nmi(captured: torch.Tensor, reference: torch.Tensor) -> float:
    return normalized_mutual_information(captured.double().numpy(), reference.double().numpy(), bins=[EDGES, EDGES])


def _shifted_pair(image: np.ndarray, shift: int, size: int = 128):
    reference = torch.from_numpy(image[100 : 100 + size, 100 : 100 + size].astype(np.float64))
    captured = torch.from_numpy(image[100 : 100 + size, 100 + shift : 100 + shift + size].astype(np.float64))
    return captured[None, None], reference[None, None]


def test_hard_nmi_equals_scikit_image_on_random_images(dtype, generator):
    reference = torch.rand(4, 1, 40, 50, generator=generator, dtype=torch.float64) * 256
    captured = (reference + 30 * torch.randn(4, 1, 40, 50, generator=generator, dtype=torch.float64)).clamp(0, 255.5)
    scores = nmi(captured.to(dtype), reference.to(dtype), kernel="hard")
    expected = [_skimage_nmi(captured[index, 0].to(dtype), reference[index, 0].to(dtype)) for index in range(4)]
    np.testing.assert_allclose(scores.double().numpy(), expected, rtol=0, atol=1e-6)


def test_hard_nmi_equals_scikit_image_on_a_real_image(camera_image, dtype):
    for shift in (0, 1, 5):
        captured, reference = _shifted_pair(camera_image, shift)
        score = nmi(captured.to(dtype), reference.to(dtype), kernel="hard").item()
        assert score == pytest.approx(_skimage_nmi(captured[0, 0], reference[0, 0]), abs=1e-6)


def test_identical_images_score_two_and_independent_ones_near_one(generator, dtype):
    image = (torch.rand(2, 1, 256, 256, generator=generator) * 256).to(dtype)
    other = (torch.rand(2, 1, 256, 256, generator=generator) * 256).to(dtype)
    torch.testing.assert_close(nmi(image, image, kernel="hard"), torch.full((2,), 2.0, dtype=dtype))
    independent = nmi(image, other, kernel="hard")
    # The plug-in estimate's bias for 1024 joint bins and 65536 pixels is about 1e-3.
    assert ((independent > 1.0) & (independent < 1.005)).all()
    assert (enmi(image, other, 25.0) < 1.005).all()


def test_constant_images_score_one():
    constant = torch.full((1, 1, 8, 8), 100.0)
    ramp = torch.arange(64.0).reshape(1, 1, 8, 8) * 4
    torch.testing.assert_close(nmi(constant, constant, kernel="hard"), torch.ones(1))
    torch.testing.assert_close(nmi(constant, ramp, kernel="hard"), torch.ones(1))


def test_enmi_tends_to_hard_nmi_as_the_variance_vanishes(generator, dtype):
    reference = torch.rand(3, 1, 32, 32, generator=generator, dtype=torch.float64) * 256
    captured = reference + 20 * torch.randn(3, 1, 32, 32, generator=generator, dtype=torch.float64)
    hard = nmi(captured.to(dtype), reference.to(dtype), kernel="hard")
    previous = None
    for variance in (1e-1, 1e-3, 1e-6, 1e-10):
        gap = (enmi(captured.to(dtype), reference.to(dtype), variance, kernel="mass") - hard).abs().max()
        assert previous is None or gap <= previous + 1e-7
        previous = gap
    assert previous < 1e-6
    torch.testing.assert_close(enmi(captured.to(dtype), reference.to(dtype), 1e-8, kernel="density"), hard)


@pytest.mark.parametrize("score", ["nmi", "enmi"])
def test_score_falls_monotonically_as_the_shift_grows(camera_image, score, generator):
    scores = []
    noise = 15 * torch.randn(1, 1, 128, 128, generator=generator, dtype=torch.float64)
    for shift in range(7):
        captured, reference = _shifted_pair(camera_image, shift)
        captured = captured + noise
        value = nmi(captured, reference, kernel="hard") if score == "nmi" else enmi(captured, reference, 225.0)
        scores.append(value.item())
    assert all(later < earlier for earlier, later in itertools.pairwise(scores)), scores


def test_bijective_relabelling_of_bins_leaves_hard_nmi_unchanged(camera_image, generator):
    captured, reference = _shifted_pair(camera_image, 2)
    permutation = torch.randperm(32, generator=generator)
    relabelled = (permutation[(reference // 8).long()] * 8 + 4).double()
    torch.testing.assert_close(
        nmi(captured, relabelled, kernel="hard"), nmi(captured, reference, kernel="hard"), rtol=0, atol=1e-12
    )
    torch.testing.assert_close(
        nmi(relabelled, captured, kernel="hard"), nmi(reference, captured, kernel="hard"), rtol=0, atol=1e-12
    )


def test_batch_equals_loop(generator):
    reference = torch.rand(4, 1, 16, 16, generator=generator, dtype=torch.float64) * 256
    captured = reference + 10 * torch.randn(4, 1, 16, 16, generator=generator, dtype=torch.float64)
    variance = torch.rand(4, 1, 16, 16, generator=generator, dtype=torch.float64) * 100 + 1
    batched = enmi(captured, reference, variance)
    looped = torch.cat([enmi(captured[i : i + 1], reference[i : i + 1], variance[i : i + 1]) for i in range(4)])
    torch.testing.assert_close(batched, looped, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("score", ["nmi", "enmi"])
def test_masked_equals_cropped(generator, score):
    reference = torch.rand(2, 1, 20, 24, generator=generator, dtype=torch.float64) * 256
    captured = reference + 10 * torch.randn(2, 1, 20, 24, generator=generator, dtype=torch.float64)
    valid = torch.zeros(2, 1, 20, 24, dtype=torch.bool)
    valid[0, :, 3:15, 5:20] = True
    valid[1, :, 0:10, 0:10] = True
    masked = (
        nmi(captured, reference, valid_mask=valid, kernel="hard")
        if score == "nmi"
        else enmi(captured, reference, 40.0, valid_mask=valid)
    )
    crops = [(0, slice(3, 15), slice(5, 20)), (1, slice(0, 10), slice(0, 10))]
    for sample, rows, columns in crops:
        part = (slice(sample, sample + 1), slice(None), rows, columns)
        cropped = (
            nmi(captured[part], reference[part], kernel="hard")
            if score == "nmi"
            else enmi(captured[part], reference[part], 40.0)
        )
        torch.testing.assert_close(masked[sample : sample + 1], cropped, rtol=1e-12, atol=1e-12)


def test_streaming_joint_histograms_give_the_whole_score(generator):
    reference = torch.rand(6, 1, 16, 16, generator=generator, dtype=torch.float64) * 256
    captured = reference + 30 * torch.randn(6, 1, 16, 16, generator=generator, dtype=torch.float64)
    summed = joint_histogram(captured[:3], reference[:3], captured_variance=50.0) + joint_histogram(
        captured[3:], reference[3:], captured_variance=50.0
    )
    whole = enmi(captured.reshape(1, 1, 96, 16)[:, :, :48], reference.reshape(1, 1, 96, 16)[:, :, :48], 50.0)
    first_half = joint_histogram(
        captured[:3].reshape(1, 1, -1), reference[:3].reshape(1, 1, -1), captured_variance=50.0
    )  # flat samples (B, 1, N)
    torch.testing.assert_close(
        summed.sum(0, keepdim=True),
        joint_histogram(captured.reshape(1, 1, -1), reference.reshape(1, 1, -1), captured_variance=50.0),
    )
    torch.testing.assert_close(nmi_from_joint_histogram(first_half), whole)


def test_entropies_of_closed_form_distributions():
    uniform = torch.ones(1, 4, 4, dtype=torch.float64)
    captured_entropy, reference_entropy, joint_entropy = entropies(uniform)
    torch.testing.assert_close(joint_entropy, torch.tensor([np.log(16)], dtype=torch.float64))
    torch.testing.assert_close(captured_entropy, torch.tensor([np.log(4)], dtype=torch.float64))
    torch.testing.assert_close(reference_entropy, torch.tensor([np.log(4)], dtype=torch.float64))
    diagonal = torch.diag(torch.tensor([1.0, 3.0], dtype=torch.float64))[None]
    expected = -(0.25 * np.log(0.25) + 0.75 * np.log(0.75))
    torch.testing.assert_close(
        torch.stack(entropies(diagonal)).flatten(), torch.full((3,), expected, dtype=torch.float64)
    )


def test_xu_kernel_nmi_equals_kornia(generator):
    # kornia maps each image's [min, max] onto the bin centres; pin min and max there so both use the same bins.
    bins, value_range = 16, (0.0, 16.0)
    reference = torch.rand(2, 24, 24, generator=generator, dtype=torch.float64) * 15 + 0.5
    captured = (reference + torch.randn(2, 24, 24, generator=generator, dtype=torch.float64)).clamp(0.5, 15.5)
    for image in (reference, captured):
        image[:, 0, 0], image[:, 0, 1] = 0.5, 15.5
    ours = nmi(captured, reference, bins=bins, value_range=value_range, kernel="xu", reference_kernel="xu")
    theirs = -normalized_mutual_information_loss_2d(captured, reference, num_bins=bins)
    torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-5)


@pytest.mark.parametrize("weights", ["mass", "density"])
def test_gradcheck_enmi_captured_and_variance(generator, weights):
    reference = torch.rand(2, 1, 6, 6, generator=generator, dtype=torch.float64) * 256
    captured = (reference + 20 * torch.randn(2, 1, 6, 6, generator=generator, dtype=torch.float64)).requires_grad_()
    variance = (torch.rand(1, 1, 6, 6, generator=generator, dtype=torch.float64) * 300 + 10).requires_grad_()
    valid = torch.rand(2, 1, 6, 6, generator=generator) > 0.2
    assert gradcheck(
        lambda values, noise: enmi(values, reference, noise, bins=8, kernel=weights, valid_mask=valid),
        (captured, variance),
    )


def test_gradcheck_soft_nmi_captured_and_reference(generator):
    reference = (torch.rand(2, 1, 6, 6, generator=generator, dtype=torch.float64) * 256).requires_grad_()
    captured = (torch.rand(2, 1, 6, 6, generator=generator, dtype=torch.float64) * 256).requires_grad_()
    assert gradcheck(
        lambda values, map_values: nmi(values, map_values, bins=8, kernel="triangular", reference_kernel="triangular"),
        (captured, reference),
    )


def test_empty_bins_and_tiny_variances_give_finite_values_and_gradients():
    captured = torch.tensor([[[10.0, 10.0, 200.0, 201.0]]], requires_grad=True)  # flat samples (B, 1, N)
    reference = torch.tensor([[[10.0, 10.0, 200.0, 200.0]]])
    variance = torch.tensor([1e-30, 1e-12, 1e-6, 1.0], requires_grad=True)
    score = enmi(captured, reference, variance, bins=64)
    score.sum().backward()
    assert torch.isfinite(score).all() and torch.isfinite(captured.grad).all() and torch.isfinite(variance.grad).all()


def test_torch_compile_agrees_with_eager(generator):
    reference = torch.rand(2, 1, 16, 16, generator=generator) * 256
    captured = reference + 10 * torch.randn(2, 1, 16, 16, generator=generator)
    compiled = torch.compile(lambda a, b: enmi(a, b, 50.0, bins=16), backend="aot_eager", fullgraph=False)
    torch.testing.assert_close(compiled(captured, reference), enmi(captured, reference, 50.0, bins=16))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_forward_matches_cpu_without_host_sync(generator):
    reference = torch.rand(2, 1, 64, 64, generator=generator) * 256
    captured = reference + 10 * torch.randn(2, 1, 64, 64, generator=generator)
    variance = torch.rand(1, 1, 64, 64, generator=generator) * 100 + 1
    expected = enmi(captured, reference, variance)
    cuda_inputs = [tensor.cuda() for tensor in (captured, reference, variance)]
    enmi(*cuda_inputs)
    torch.cuda.set_sync_debug_mode("error")
    try:
        result = enmi(*cuda_inputs)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    torch.testing.assert_close(result.cpu(), expected)


IMAGE = torch.rand(2, 1, 4, 4) * 256
INVALID_INPUTS = [
    ({"captured": [1, 2]}, TypeError, "captured must be a torch.Tensor, got list"),
    ({"captured": IMAGE.long()}, TypeError, "captured must be a floating-point tensor, got dtype torch.int64"),
    ({"reference": IMAGE[:, :, :3]}, ValueError, r"reference must have the shape of captured \(2, 1, 4, 4\)"),
    ({"captured": IMAGE.expand(2, 3, 4, 4), "reference": IMAGE.expand(2, 3, 4, 4)}, ValueError, "one channel"),
    ({"captured": IMAGE.masked_fill(IMAGE > 200, float("nan"))}, ValueError, "captured must be finite"),
    ({"reference": IMAGE.masked_fill(IMAGE > 200, float("inf"))}, ValueError, "reference must be finite"),
    ({"variance": torch.zeros(4, 4)}, ValueError, "variance must be finite and > 0"),
    ({"variance": -1.0}, ValueError, "variance must be finite and > 0"),
    ({"variance": torch.ones(3, 4)}, ValueError, r"variance must have the spatial shape of captured \(4, 4\)"),
    ({"variance": torch.ones(3, 1, 4, 4)}, ValueError, "^variance must have the spatial shape"),
    ({"variance": None}, ValueError, "variance must be a number or a tensor"),
    ({"bins": 1}, ValueError, "bins must be an int >= 2, got 1"),
    ({"bins": 8.0}, TypeError, "bins must be an int >= 2"),
    ({"valid_mask": torch.zeros(4, 4, dtype=torch.bool)}, ValueError, "valid_mask selects no pixel"),
    ({"valid_mask": torch.ones(4, 4)}, TypeError, "valid_mask must be a bool tensor, got dtype torch.float32"),
    ({"value_range": (5.0, 5.0)}, ValueError, "value_range must be finite with low < high"),
    ({"value_range": (0.0, float("inf"))}, ValueError, "value_range must be finite"),
    ({"value_range": 3}, ValueError, "value_range must be a pair of finite numbers"),
    ({"kernel": "gaussian"}, ValueError, r"kernel must be one of \['mass', 'density', 'truncated'\], got 'gaussian'"),
    ({"reference_kernel": "soft"}, ValueError, "reference_kernel must be one of"),
    ({"log_prior": torch.zeros(5)}, ValueError, r"log_prior must have shape \(32,\)"),
]


@pytest.mark.parametrize(("overrides", "error", "message"), INVALID_INPUTS)
def test_invalid_inputs_raise_clear_errors(overrides, error, message):
    arguments = {"captured": IMAGE, "reference": IMAGE, "variance": 10.0, **overrides}
    with pytest.raises(error, match=message):
        enmi(arguments.pop("captured"), arguments.pop("reference"), arguments.pop("variance"), **arguments)


def test_nmi_rejects_likelihood_kernels_and_unknown_kernels():
    with pytest.raises(ValueError, match=r"kernel must be one of \['hard', 'triangular', 'xu'\], got 'mass'"):
        nmi(IMAGE, IMAGE, kernel="mass")
    with pytest.raises(ValueError, match="kernel='mass' needs captured_variance"):
        joint_histogram(IMAGE, IMAGE, kernel="mass")
    with pytest.raises(ValueError, match="captured_variance is only used by kernels"):
        joint_histogram(IMAGE, IMAGE, kernel="hard", captured_variance=1.0)


def test_value_checks_can_be_enabled_for_accelerators():
    with value_checks(True), pytest.raises(ValueError, match="captured must be finite"):
        nmi(IMAGE.masked_fill(IMAGE > 100, float("nan")), IMAGE, kernel="hard")


@pytest.mark.slow
def test_inductor_compiled_loss_and_gradient_agree_with_eager(generator):
    reference = torch.rand(2, 1, 32, 32, generator=generator) * 256
    captured = reference + 10 * torch.randn(2, 1, 32, 32, generator=generator)
    variance = torch.rand(1, 1, 32, 32, generator=generator) * 100 + 1

    def score_and_gradient(function):
        values = captured.clone().requires_grad_()
        score = function(values, reference, variance)
        (gradient,) = torch.autograd.grad(score.sum(), values)
        return score, gradient

    eager = score_and_gradient(enmi)
    compiled = score_and_gradient(torch.compile(enmi))
    for got, want in zip(compiled, eager, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-6)


def test_autocast_computes_in_float32(generator):
    reference = torch.rand(2, 1, 16, 16, generator=generator) * 256
    captured = reference + 10 * torch.randn(2, 1, 16, 16, generator=generator)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        score = enmi(captured, reference, 50.0)
    assert score.dtype == torch.float32
    torch.testing.assert_close(score, enmi(captured, reference, 50.0))


def _numpy_weighted_nmi(counts):
    probability = counts / counts.sum()

    def entropy(p):
        p = p[p > 0]
        return -(p * np.log(p)).sum()

    return (entropy(probability.sum(1)) + entropy(probability.sum(0))) / entropy(probability)


def test_enmi_with_reliability_equals_a_weighted_numpy_histogram(dtype, tolerance):
    from enmi_torch.binning import likelihood_weights, reliability_weights

    generator = torch.Generator().manual_seed(4)
    reference = torch.rand(2, 1, 6, 9, generator=generator, dtype=torch.float64) * 256
    variance = torch.logspace(0, 3, 54, dtype=torch.float64).reshape(1, 1, 6, 9)
    captured = reference + torch.randn(reference.shape, generator=generator, dtype=torch.float64) * variance.sqrt()
    valid = torch.rand(2, 1, 6, 9, generator=generator) > 0.2
    result = enmi(
        captured.to(dtype), reference.to(dtype), variance.to(dtype), bins=6, valid_mask=valid, reliability=True
    )
    for sample in range(2):
        keep = valid[sample].flatten()
        values, variances = captured[sample].flatten(), variance.flatten()
        weight = reliability_weights(values[None], variances[None], keep[None])[0].numpy()
        spread = likelihood_weights(values, variances, 6, (0.0, 256.0), "mass").numpy()
        bins = np.clip((reference[sample].flatten().numpy() // (256 / 6)).astype(int), 0, 5)
        counts = np.zeros((6, 6))
        for pixel in np.flatnonzero(keep.numpy()):
            counts[:, bins[pixel]] += weight[pixel] * spread[pixel]
        assert result[sample].item() == pytest.approx(_numpy_weighted_nmi(counts), rel=tolerance["rtol"] * 10)
    # With one variance for every pixel the weights are all equal: the score does not change.
    plain = enmi(captured, reference, 90.0, bins=6, valid_mask=valid)
    torch.testing.assert_close(enmi(captured, reference, 90.0, bins=6, valid_mask=valid, reliability=True), plain)
    # ... while a strongly non-uniform variance changes it.
    assert not torch.allclose(result.double(), enmi(captured, reference, variance, bins=6, valid_mask=valid), rtol=1e-3)


def test_enmi_with_reliability_has_finite_gradients():
    generator = torch.Generator().manual_seed(5)
    reference = torch.rand(1, 1, 4, 5, generator=generator, dtype=torch.float64) * 256
    captured = (
        reference + torch.randn(reference.shape, generator=generator, dtype=torch.float64) * 20
    ).requires_grad_()
    variance = torch.linspace(5, 900, 20, dtype=torch.float64).reshape(1, 1, 4, 5)

    def score(captured):
        return enmi(captured, reference, variance, bins=5, reliability=True)

    assert torch.autograd.gradcheck(score, (captured,))
    with pytest.raises(TypeError, match="reliability must be True or False"):
        enmi(captured, reference, variance, reliability="yes")


def test_truncated_weights_keep_the_tails_out_of_the_edge_bins_and_tend_to_nmi(dtype, tolerance):
    generator = torch.Generator().manual_seed(6)
    reference = torch.rand(2, 1, 8, 6, generator=generator, dtype=dtype) * 256
    captured = reference + torch.randn(reference.shape, generator=generator, dtype=dtype) * 3
    # Variance to 0: a unit count in the pixel's bin, the hard NMI (values kept away from bin edges).
    centred = (captured // 16) * 16 + 8
    tiny = enmi(centred, reference, 1e-6, bins=16, kernel="truncated")
    torch.testing.assert_close(tiny, nmi(centred, reference, bins=16, kernel="hard"), **tolerance)
    # Far from the range's ends the truncated and the folded masses agree; near them they do not.
    inner = enmi(centred.clamp(40, 200), reference, 4.0, bins=16, kernel="truncated")
    torch.testing.assert_close(inner, enmi(centred.clamp(40, 200), reference, 4.0, bins=16), **tolerance)
    edge = 225 + reference / 10
    folded = enmi(edge, reference, 400.0, bins=16, kernel="mass")
    truncated = enmi(edge, reference, 400.0, bins=16, kernel="truncated")
    assert not torch.allclose(folded, truncated, rtol=1e-3)
