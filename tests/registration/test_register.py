"""Registration by Gauss-Newton through a score: exact recovery, gradients, pixels off the map, batching, refusals."""

from __future__ import annotations

import itertools
from functools import partial

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from enmi_torch import ECR, NCC, NMI, Localization, localize
from enmi_torch.registration import register, registration_score, warp_reference

SHAPE = (20, 28)  # non-square captured images: a swapped axis fails


def _map(generator: torch.Generator, shape=(70, 90)) -> torch.Tensor:
    noise = torch.rand(1, 1, shape[0] + 2, shape[1] + 2, generator=generator, dtype=torch.float64)
    smooth = F.avg_pool2d(noise, 3, 1)
    return (smooth - smooth.min()) / (smooth.max() - smooth.min()) * 250 + 2


def test_warp_reference_follows_localization_local_to_map(generator):
    from scipy import ndimage

    reference = _map(generator)
    pose = torch.tensor([[40.3, 31.7, 23.0], [52.0, 40.0, -60.0]], dtype=torch.float64)
    warped, valid = warp_reference(reference, pose, SHAPE, interpolation="bilinear")
    spline, _ = warp_reference(reference, pose, SHAPE)
    transform = Localization(pose, *(torch.zeros(2),) * 5).local_to_map(SHAPE)
    for sample, (row, col) in enumerate([(3, 25), (17, 2)]):
        x, y, _ = (transform[sample] @ torch.tensor([col, row, 1.0], dtype=torch.float64)).tolist()
        # bilinear interpolation at (x, y), written out
        x0, y0 = int(x), int(y)
        fx, fy = x - x0, y - y0
        block = reference[0, 0, y0 : y0 + 2, x0 : x0 + 2]
        expected = (1 - fy) * ((1 - fx) * block[0, 0] + fx * block[0, 1]) + fy * (
            (1 - fx) * block[1, 0] + fx * block[1, 1]
        )
        assert float(warped[sample, 0, row, col]) == pytest.approx(float(expected), abs=1e-9)
        # The cubic B-spline through the cells, mirrored beyond the border: scipy's spline of order 3.
        cubic = ndimage.map_coordinates(reference[0, 0].numpy(), [[y], [x]], order=3, mode="mirror")[0]
        assert float(spline[sample, 0, row, col]) == pytest.approx(float(cubic), abs=1e-9)
    assert bool(valid.all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(
    "score",
    [ECR(bins=16), ECR(response="linear"), ECR(bins=16, misfit="regional"), NCC()],
    ids=["ecr", "ecr-linear", "ecr-regional", "ncc"],
)
def test_a_noiseless_sub_cell_pose_is_recovered(generator, dtype, score):
    reference = _map(generator)
    truth = torch.tensor([[44.37, 33.81, 2.63], [40.9, 36.2, -3.4]], dtype=torch.float64)
    captured = warp_reference(reference, truth, SHAPE)[0].to(dtype)
    start = truth.round()  # localize's integer peak
    variance = None if isinstance(score, NCC) else 4.0
    found = register(captured, reference.to(dtype), variance, pose=start.to(dtype), score=score)
    error = (found.pose.double() - truth).abs()
    tolerance = 1e-3 if dtype == torch.float64 else 5e-3
    assert float(error[:, :2].max()) < tolerance
    assert float(error[:, 2].max()) < 10 * tolerance  # degrees
    assert bool(found.converged.all())
    assert found.pose.dtype == dtype


def test_the_score_is_best_at_the_truth_and_its_gradient_matches_finite_differences(generator):
    reference = _map(generator)
    truth = torch.tensor([[44.37, 33.81, 2.63]], dtype=torch.float64)
    captured = warp_reference(reference, truth, SHAPE)[0] + torch.randn(1, 1, *SHAPE, generator=generator)
    score = ECR(bins=16, model_variance=4.0)
    pose = (truth + torch.tensor([[0.23, -0.31, 0.7]], dtype=torch.float64)).requires_grad_(True)

    def value(at):
        return registration_score(captured, reference, at, 1.0, score=score)

    assert bool(value(truth) > value(pose.detach()))
    (gradient,) = torch.autograd.grad(value(pose).sum(), pose)
    for axis, step in ((0, 1e-5), (1, 1e-5), (2, 1e-4)):
        offset = torch.zeros(1, 3, dtype=torch.float64)
        offset[0, axis] = step
        numeric = (value(pose.detach() + offset) - value(pose.detach() - offset)) / (2 * step)
        assert float(gradient[0, axis]) == pytest.approx(float(numeric), rel=1e-4, abs=1e-8)


def test_pixels_warped_in_from_off_the_map_do_not_count(generator):
    # The captured image hangs 6 cells over the map's left edge: those pixels hold garbage and no mask says so.
    reference = _map(generator)
    truth = torch.tensor([[9.4, 30.2, 0.0]], dtype=torch.float64)
    captured = warp_reference(reference, truth, SHAPE)[0]
    _, on_map = warp_reference(reference, truth, SHAPE)
    assert not bool(on_map.all())
    captured = torch.where(on_map, captured, 1e6)
    found = register(captured, reference, 1.0, pose=truth.round(), score=ECR(bins=16), margin=1.0)
    assert found.pose[0, :2].tolist() == pytest.approx(truth[0, :2].tolist(), abs=1e-3)
    masked = register(
        captured, reference, 1.0, pose=truth.round(), score=ECR(bins=16), captured_mask=on_map, margin=1.0
    )
    torch.testing.assert_close(masked.pose, found.pose, atol=1e-4, rtol=0)  # both converged (steps < 1e-4)


def test_unobserved_map_cells_do_not_count(generator):
    reference = _map(generator)
    truth = torch.tensor([[44.4, 33.8, 1.0]], dtype=torch.float64)
    captured = warp_reference(reference, truth, SHAPE)[0]
    observed = torch.ones_like(reference, dtype=torch.bool)
    observed[..., 30:40, 30:44] = False
    spoiled = torch.where(observed, reference, 0.0)  # the unobserved cells hold nothing true
    found = register(captured, spoiled, 1.0, pose=truth.round(), score=ECR(bins=16), reference_mask=observed)
    assert found.pose[0, :2].tolist() == pytest.approx(truth[0, :2].tolist(), abs=1e-3)


def test_batched_equals_one_at_a_time(generator):
    reference = _map(generator)
    truth = torch.tensor([[44.3, 33.8, 2.6], [40.9, 36.2, -3.4], [50.5, 30.5, 0.0]], dtype=torch.float64)
    captured = warp_reference(reference, truth, SHAPE)[0] + 3 * torch.randn(3, 1, *SHAPE, generator=generator)
    start = truth.round()
    together = register(captured, reference, 9.0, pose=start, score=ECR(bins=16))
    for sample in range(3):
        alone = register(
            captured[sample : sample + 1], reference, 9.0, pose=start[sample : sample + 1], score=ECR(bins=16)
        )
        torch.testing.assert_close(together.pose[sample], alone.pose[0], atol=1e-9, rtol=0)


def test_registration_refuses_what_it_cannot_fit(generator):
    reference = _map(generator)
    captured, start = reference[..., :20, :28], torch.tensor([[14.0, 10.0, 0.0]], dtype=torch.float64)
    refusal = r"register needs a score with the 'least_squares' trait .* got score=NMI\(.*have it: ecr, ncc"
    with pytest.raises(ValueError, match=refusal):
        register(captured, reference, pose=start, score=NMI())
    with pytest.raises(ValueError, match="variance is not used by score 'ncc'"):
        register(captured, reference, 1.0, pose=start, score="ncc")
    with pytest.raises(ValueError, match=r"pose must have shape \(1, 3\), rows \(x, y, yaw\), got \(2, 3\)"):
        register(captured, reference, 1.0, pose=torch.zeros(2, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="blur must be a non-empty sequence"):
        register(captured, reference, 1.0, pose=start, blur=())


def test_localize_refines_its_peak_on_request(generator):
    # Nearest-neighbour turns cannot tell yaws within about a degree apart on a small image: the grid's yaw is off,
    # the refinement finds the truth.
    reference = _map(generator, (90, 90))
    truth = torch.tensor([[44.3, 40.6, 1.3]], dtype=torch.float64)
    captured = warp_reference(reference, truth, SHAPE)[0].float()
    options = {"shifts": 5, "around": (44, 40), "yaws": [-2.0, -1.0, 0.0, 1.0, 2.0]}
    grid = localize(captured, reference.float(), 1.0, **options)
    refined = localize(captured, reference.float(), 1.0, refine=True, **options)
    expected = truth[0].tolist()
    assert refined.pose[0].tolist() == pytest.approx(expected, abs=2e-3)
    assert refined.shift[0].tolist() == pytest.approx([0.3, 0.6], abs=2e-3)
    assert float((grid.pose[0] - torch.tensor(expected)).abs().max()) > 0.1
    torch.testing.assert_close(refined.surface, grid.surface)  # the search's own results stay


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_score_is_half_the_weighted_variance_the_fit_removes_per_pixel(generator, dtype):
    # At the truth a noiseless linear map is fitted exactly: the score is half the weighted variance of the captured
    # values about their weighted mean, per counted pixel (a direct sum with other weights per pixel).
    reference = _map(generator)
    truth = torch.tensor([[44.4, 33.8, 1.0]], dtype=torch.float64)
    captured = 3 + 0.5 * warp_reference(reference, truth, SHAPE)[0]
    variance = 1 + torch.rand(1, 1, *SHAPE, generator=generator, dtype=torch.float64) * 9
    value = registration_score(
        captured.to(dtype),
        reference.to(dtype),
        truth,
        variance.to(dtype),
        score=ECR(response="linear", model_variance=2.0),
        blur=0.0,
    )
    weights = 1 / (variance + 2.0)
    mean = (weights * captured).sum() / weights.sum()
    expected = 0.5 * (weights * (captured - mean) ** 2).sum() / captured.numel()
    assert float(value) == pytest.approx(float(expected), rel=1e-4 if dtype == torch.float32 else 1e-9)


def test_the_margin_bounds_the_move(generator):
    reference = _map(generator)
    truth = torch.tensor([[44.4, 33.8, 1.0]], dtype=torch.float64)
    captured = warp_reference(reference, truth, SHAPE)[0]
    start = truth + torch.tensor([[0.9, 0.0, 0.0]], dtype=torch.float64)
    held = register(captured, reference, 1.0, pose=start, score=ECR(bins=16), margin=0.5)
    assert float((held.pose[0, 0] - start[0, 0]).abs()) <= 0.5 and not bool(held.converged[0])
    free = register(captured, reference, 1.0, pose=start, score=ECR(bins=16), margin=2.0)
    assert free.pose[0, :2].tolist() == pytest.approx(truth[0, :2].tolist(), abs=1e-3)
    for margin in (0.0, -1.0):
        with pytest.raises(ValueError, match=r"margin must be a finite number > 0 \(the largest move, in cells\)"):
            register(captured, reference, 1.0, pose=truth.round(), margin=margin)


# Inputs by name, the memory budget, and the thin places: the guard against ending below the start, the yaw Jacobian,
# the map's right and bottom borders.


def _inputs(generator):
    reference = _map(generator, (64, 64))
    pose = torch.tensor([[32.0, 32.0, 0.0]], dtype=torch.float64)
    captured = warp_reference(reference, pose, (16, 16))[0] + torch.randn(1, 1, 16, 16, generator=generator)
    return captured, reference, pose


BAD_REGISTRATION_INPUTS = [
    ({"pose": lambda pose: pose[0]}, ValueError, r"pose must have shape \(1, 3\), rows \(x, y, yaw\), got \(3,\)"),
    (
        {"pose": lambda pose: pose[:, :2]},
        ValueError,
        r"pose must have shape \(1, 3\), rows \(x, y, yaw\), got \(1, 2\)",
    ),
    ({"pose": lambda pose: pose.long()}, TypeError, "pose must be a floating-point tensor, got dtype torch.int64"),
    ({"pose": lambda pose: pose.fill_(float("nan"))}, ValueError, "pose must be finite, got NaN or inf"),
    ({"pose": lambda pose: pose.to("meta")}, ValueError, "pose must hold data, got a meta tensor"),
    ({"captured": lambda captured: captured.to("meta")}, ValueError, "captured must hold data, got a meta tensor"),
    (
        {"captured": lambda captured: captured[0, 0]},
        ValueError,
        r"captured must have shape \(B, 1, h, w\), got \(16, 16\)",
    ),
    ({"reference": lambda reference: reference[0, 0]}, ValueError, r"reference must have shape \(1, 1, Hm, Wm\) with"),
    ({"reference": lambda reference: reference.to(torch.complex128)}, TypeError, "reference must be a floating-point"),
    ({"reference": lambda reference: reference.to("meta")}, ValueError, "reference must hold data, got a meta tensor"),
    (
        {"variance": lambda _: torch.ones(1, 1, 8, 8, dtype=torch.float64)},
        ValueError,
        r"variance must have the spatial shape of captured \(16, 16\)",
    ),
    ({"variance": lambda _: -1.0}, ValueError, "variance must be finite and > 0"),
    (
        {"captured_mask": lambda _: torch.ones(1, 1, 8, 8, dtype=torch.bool)},
        ValueError,
        r"captured_mask must be as large as captured, \(1, 1, 16, 16\) or \(16, 16\), got \(1, 1, 8, 8\)",
    ),
    ({"captured_mask": lambda _: torch.ones(1, 1, 16, 16)}, TypeError, "captured_mask must be a bool tensor"),
    (
        {"reference_mask": lambda _: torch.ones(1, 1, 32, 32, dtype=torch.bool)},
        ValueError,
        r"reference_mask must be as large as reference, \(1, 1, 64, 64\) or \(64, 64\), got \(1, 1, 32, 32\)",
    ),
    ({"margin": lambda _: -5.0}, ValueError, r"margin must be a finite number"),
    ({"margin": lambda _: float("nan")}, ValueError, r"margin must be a finite number"),
    ({"margin": lambda _: True}, TypeError, r"margin must be a finite number"),
]


@pytest.mark.parametrize("function", ["register", "registration_score"])
@pytest.mark.parametrize(("change", "error", "match"), BAD_REGISTRATION_INPUTS)
def test_bad_inputs_are_refused_naming_the_argument(generator, function, change, error, match):
    captured, reference, pose = _inputs(generator)
    arguments = {"captured": captured, "reference": reference, "pose": pose, "variance": 1.0}
    options = {"score": ECR(bins=16)}
    for name, make in change.items():
        if name in arguments:
            arguments[name] = make(arguments[name].clone() if isinstance(arguments[name], torch.Tensor) else None)
        else:
            options[name] = make(None)
    if function == "register" and options.get("margin") == -5.0:
        match = r"margin must be a finite number > 0 \(the largest move, in cells\)"
    with pytest.raises(error, match=match):
        if function == "register":
            register(
                arguments["captured"], arguments["reference"], arguments["variance"], pose=arguments["pose"], **options
            )
        else:
            registration_score(
                arguments["captured"], arguments["reference"], arguments["pose"], arguments["variance"], **options
            )


@pytest.mark.parametrize(
    ("pose", "mask", "match"),
    [
        ([[500.0, 500.0, 0.0]], None, r"no captured pixel counts at pose \[500.0, 500.0, 0.0\] \(sample\(s\) \[0\]\)"),
        ([[32.0, 32.0, 0.0]], False, r"no captured pixel counts .* or are masked out by captured_mask"),
    ],
)
def test_a_pose_where_no_pixel_counts_is_named_not_a_valid_mask(generator, pose, mask, match):
    captured, reference, _ = _inputs(generator)
    pose = torch.tensor(pose, dtype=torch.float64)
    captured_mask = None if mask is None else torch.zeros(1, 1, 16, 16, dtype=torch.bool)
    for call in (
        lambda: register(captured, reference, 1.0, pose=pose, captured_mask=captured_mask),
        lambda: registration_score(captured, reference, pose, 1.0, captured_mask=captured_mask),
    ):
        with pytest.raises(ValueError, match=match) as error:
            call()
        assert "valid_mask" not in str(error.value)


def test_the_registration_score_counts_no_sample_off_the_map_with_a_margin_of_zero(generator):
    # Before, margin=-5 counted 48 zero-padded samples off the map; margin=0 keeps every counted sample on it.
    captured, reference, _ = _inputs(generator)
    pose = torch.tensor([[4.0, 32.0, 0.0]], dtype=torch.float64)
    _, valid = warp_reference(reference, pose, (16, 16), margin=0.0)
    assert int((~valid).sum()) == 4 * 16  # columns -4 .. -1 of the map
    masked = registration_score(captured, reference, pose, 1.0, captured_mask=valid, score=ECR(bins=16))
    assert float(registration_score(captured, reference, pose, 1.0, score=ECR(bins=16))) == float(masked)


def test_warp_reference_takes_integer_sizes_only_and_refuses_a_small_mask(generator):
    reference = _map(generator, (64, 64))
    pose = torch.tensor([[32.0, 32.0, 0.0]], dtype=torch.float64)
    for shape in ((4.5, 4), (0, 4), (4,), "44"):
        with pytest.raises(ValueError, match=r"shape must be \(H, W\), two positive ints"):
            warp_reference(reference, pose, shape)
    with pytest.raises(ValueError, match="reference_mask must be as large as reference"):
        warp_reference(reference, pose, (4, 4), torch.ones(1, 1, 32, 32, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"margin must be a finite number >= 0"):
        warp_reference(reference, pose, (4, 4), margin=-3.0)
    with pytest.raises(ValueError, match=r"margin must be a finite number >= 0"):
        warp_reference(reference, pose, (4, 4), margin=float("nan"))
    with pytest.raises(TypeError, match=r"reference must be a floating-point tensor, got dtype torch\.complex128"):
        warp_reference(reference.to(torch.complex128), pose, (4, 4))  # its imaginary part was dropped


def test_nan_map_cells_count_as_unobserved_like_a_mask_says(generator):
    reference = _map(generator, (64, 64))
    holed = reference.clone()
    holed[..., 30:34, 28:31] = float("nan")
    observed = torch.isfinite(holed)
    pose = torch.tensor([[32.3, 31.6, 7.0]], dtype=torch.float64)
    warped, valid = warp_reference(holed, pose, (16, 12))
    masked_warped, masked_valid = warp_reference(torch.where(observed, holed, 0.0), pose, (16, 12), observed)
    assert not bool(valid.all()) and torch.equal(valid, masked_valid)
    assert bool(torch.isfinite(warped).all())
    torch.testing.assert_close(warped[valid], masked_warped[masked_valid])
    truth = torch.tensor([[32.3, 31.6, 2.0]], dtype=torch.float64)
    captured = warp_reference(reference, truth, (20, 28))[0]
    found = register(captured, holed, 1.0, pose=truth.round(), score=ECR(bins=16), blur=(1.0, 0.0))
    assert found.pose[0, :2].tolist() == pytest.approx(truth[0, :2].tolist(), abs=1e-3)


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda c, r, p: register(c, r, 1.0, pose=p, score=ECR(bins=100000)), r"bins=100000 needs about .* GiB"),
        (lambda c, r, p: registration_score(c, r, p, 1.0, score=ECR(bins=100000)), r"bins=100000 needs about"),
        (lambda c, r, p: register(c, r, 1.0, pose=p, blur=(1e6, 0.0)), r"blur=\(1000000.0, 0.0\) needs about"),
        (lambda c, r, p: warp_reference(r, p, (100000, 100000)), r"shape=\(100000, 100000\) needs about"),
    ],
)
def test_what_would_not_fit_the_memory_budget_is_refused_before_allocating(generator, call, match):
    from enmi_torch.utils.budget import MemoryBudgetError

    captured, reference, pose = _inputs(generator)
    with pytest.raises(MemoryBudgetError, match=match):
        call(captured, reference, pose)


def test_a_result_scoring_below_its_start_is_replaced_by_the_start(generator, monkeypatch):
    from enmi_torch.registration import stage

    reference = _map(generator)
    truth = torch.tensor([[44.37, 33.81, 2.63], [40.9, 36.2, -3.4]], dtype=torch.float64)
    captured = warp_reference(reference, truth, SHAPE)[0]
    # The blurred stage "leads astray": it ends 0.6 cells off for the first image, on the truth for the second.
    led = truth + torch.tensor([[0.6, 0.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    monkeypatch.setattr(
        stage.Stage,
        "run",
        lambda self, fit, pose, start, iterations, tolerance: (
            led,
            torch.ones(2, dtype=torch.int64),
            torch.ones(2, dtype=torch.bool),
            self.score_with(fit, led),
            self.score_with(fit, pose),
        ),
    )
    start = truth + torch.tensor([[0.0, 0.0, 0.0], [0.4, -0.3, 0.5]], dtype=torch.float64)
    start[0] = truth[0]  # the first starts on the truth: the stage's result scores below it
    found = register(captured, reference, 1.0, pose=start, score=ECR(bins=16), blur=(0.0,))
    torch.testing.assert_close(found.pose[0], truth[0], atol=0, rtol=0)  # the start, exactly
    torch.testing.assert_close(found.pose[1], truth[1], atol=0, rtol=0)  # a better result is kept
    assert found.converged.tolist() == [False, True]


@pytest.mark.parametrize("interpolation", ["bspline", "bilinear"])
def test_the_pose_jacobian_is_the_derivative_of_the_samples_at_a_non_zero_yaw(generator, interpolation):
    # The closed-form Jacobian against autograd through the samples (themselves differentiable in the positions).
    from enmi_torch.registration.stage import Stage
    from enmi_torch.registration.warp import sample_positions

    reference = _map(generator)
    pose = torch.tensor([[44.37, 33.81, 31.0], [40.9, 36.2, -57.0]], dtype=torch.float64)
    captured = warp_reference(reference, pose + 0.3, SHAPE)[0]
    score = ECR(response="linear", model_variance=1.0)
    stage = Stage(
        captured, reference, torch.tensor(1.0, dtype=torch.float64), None, None, score, 0.5, 2.0, interpolation
    )
    fit = stage.setup(pose)
    _, jacobian, _ = stage.residuals(fit, pose)
    sampler = stage.map.sampler

    def blurred_samples(at, sample):  # the stage's blur over the counted pixels, of one image
        samples = sampler.sample(sample_positions(at[None], SHAPE))[0][:, None]
        return stage.blurred(samples, torch.tensor([sample])).flatten()

    warped = torch.stack([blurred_samples(pose[sample], sample) for sample in range(2)])
    slope = fit.solve(stage.values.flatten(1), warped)[1]
    for sample in range(2):
        per_pose = torch.autograd.functional.jacobian(partial(blurred_samples, sample=sample), pose[sample])
        expected = -(fit.weights[sample].sqrt() * slope[sample])[:, None] * per_pose  # (N, 3): d / d (x, y, yaw)
        torch.testing.assert_close(jacobian[sample], expected, atol=1e-9, rtol=1e-7)
    assert float(jacobian[..., 2].abs().max()) > 0


@pytest.mark.parametrize("margin", [0.0, 1.5])
def test_warp_reference_counts_samples_up_to_the_right_and_bottom_borders(margin):
    height, width = 6, 9  # non-square: a swapped axis fails
    reference = torch.arange(height * width, dtype=torch.float64).reshape(1, 1, height, width)
    steps = torch.arange(-1.0, max(height, width) + 0.5, 0.25, dtype=torch.float64)
    x, y = torch.meshgrid(steps, steps, indexing="xy")
    pose = torch.stack([x.flatten(), y.flatten(), torch.zeros(x.numel(), dtype=torch.float64)], 1)
    _, valid = warp_reference(reference, pose, (1, 1), margin=margin)  # one pixel at (x, y) each
    expected = (
        (pose[:, 0] >= margin)
        & (pose[:, 0] <= width - 1 - margin)
        & (pose[:, 1] >= margin)
        & (pose[:, 1] <= height - 1 - margin)
    )
    assert valid.flatten().tolist() == expected.tolist()
    corner = torch.tensor([[width - 1.0, height - 1.0, 0.0]], dtype=torch.float64)  # the bottom-right cell itself
    corner_value, corner_valid = warp_reference(reference, corner, (1, 1))
    assert float(corner_value) == pytest.approx(height * width - 1, abs=1e-9) and bool(corner_valid)


def test_the_binned_response_is_the_weighted_least_squares_fit_of_hat_functions_at_the_bin_centres(generator):
    # An independent fit: numpy least squares on hat functions with knots at the bin centres (values beyond the first
    # and last knot held at them), each pixel weighed by 1 / (sigma^2 + tau^2).
    reference = _map(generator)
    pose = torch.tensor([[44.4, 33.8, 3.0]], dtype=torch.float64)
    captured = warp_reference(reference, pose + 0.4, SHAPE)[0] + torch.randn(1, 1, *SHAPE, generator=generator)
    variance = 1 + torch.rand(1, 1, *SHAPE, generator=generator, dtype=torch.float64) * 9
    bins, value_range, tau2 = 5, (0.0, 256.0), 3.0
    score = ECR(bins=bins, model_variance=tau2, response="binned")
    value = registration_score(captured, reference, pose, variance, score=score, blur=0.0)
    warped = warp_reference(reference, pose, SHAPE)[0].flatten().numpy()
    step = (value_range[1] - value_range[0]) / bins
    knots = value_range[0] + step * (np.arange(bins) + 0.5)
    position = np.clip((warped - knots[0]) / step, 0, bins - 1)
    design = np.maximum(0.0, 1 - np.abs(position[:, None] - np.arange(bins)[None, :]))  # hat functions
    weights = 1 / (variance.flatten().numpy() + tau2)
    values = captured.flatten().numpy()
    root = np.sqrt(weights)
    coefficients = np.linalg.lstsq(design * root[:, None], values * root, rcond=None)[0]
    residual = (weights * (values - design @ coefficients) ** 2).sum()
    mean = (weights * values).sum() / weights.sum()
    expected = 0.5 * ((weights * (values - mean) ** 2).sum() - residual) / values.size
    assert float(value) == pytest.approx(expected, rel=1e-9)


def test_the_blur_budget_counts_the_padded_images(generator):
    from enmi_torch.utils.budget import MemoryBudgetError, format_bytes, memory_budget

    captured, reference, pose = _inputs(generator)  # a 64 x 64 map, 16 x 16 captured
    radius = 300  # sigma 100: 3 sigma
    expected = 8 * 4 * (16 + 2 * radius) ** 2  # the captured image, the samples and three derivatives, padded
    with memory_budget(4_000_000), pytest.raises(MemoryBudgetError, match=rf"needs about {format_bytes(expected)} "):
        register(captured, reference, 1.0, pose=pose, blur=(100.0, 0.0))  # the map's table fits: 2 MiB


def _block_means_case(noise: float):
    """A camera photograph's 3 x 3 block means: an 80 x 80 map and 48 x 48 captured images moved by whole source
    pixels (the truth a whole number of thirds of a cell), noise of standard deviation ``noise``, clipped."""
    from skimage import data

    photo = torch.from_numpy(data.camera().astype(np.float64))

    def blocks(image):
        return F.avg_pool2d(image[None, None], 3)[0]

    moves = [(1, 2), (-2, 1), (4, -5), (-1, -1), (5, 3), (2, -4), (-4, 2), (3, 1)]  # source pixels (x, y)
    top, left = 150, 120
    reference = blocks(photo[top : top + 240, left : left + 240])[None]
    captured = torch.stack(
        [blocks(photo[top + 48 + y : top + 192 + y, left + 48 + x : left + 192 + x]) for x, y in moves]
    )
    truth = torch.tensor([[40 + x / 3, 40 + y / 3, 0.0] for x, y in moves], dtype=torch.float64)
    generator = torch.Generator().manual_seed(0)
    captured = (captured + noise * torch.randn(captured.shape, generator=generator, dtype=torch.float64)).clamp(
        0, 255.999
    )
    return captured, reference, truth


def test_block_means_moved_by_thirds_of_a_cell_are_found_twice_as_close_as_by_the_bilinear_unblurred_fit():
    # Mutations killed: the default interpolation bilinear, or no half-cell blur in the last stage.
    captured, reference, truth = _block_means_case(0.0)
    start = torch.cat([truth[:, :2].round(), truth[:, 2:]], 1)

    def rms(**options):
        found = register(captured, reference, 1.0, pose=start, **options)
        return float((found.pose - truth)[:, :2].square().sum(1).mean().sqrt())

    default, bilinear = rms(), rms(interpolation="bilinear", blur=(0.0,))  # 0.0095 and 0.026 cells
    assert default < 0.015
    assert default < 0.5 * bilinear
    assert rms(blur=(0.0,)) > 1.2 * default and rms(interpolation="bilinear") > 1.2 * default  # each a part


@pytest.mark.parametrize("options", [{}, {"interpolation": "bilinear", "blur": (0.0,)}], ids=["default", "bilinear"])
def test_each_image_ends_on_a_maximum_of_the_score_it_reports_and_never_below_its_start(options):
    # Mutation killed: steps accepted on the residuals' sum of squares alone (without the shrunk response's pull,
    # which the score holds): an image then stops below its start's score and is handed back unrefined.
    captured, reference, truth = _block_means_case(30.0)
    start = torch.cat([truth[:, :2].round(), truth[:, 2:]], 1)
    start[0] = truth[0]  # one starts on the truth
    found = register(captured, reference, 900.0, pose=start, **options)
    assert bool(found.converged.all())
    same = {"score": "ecr", "margin": 2.0, "blur": options.get("blur", (0.5,))[-1]}
    same["interpolation"] = options.get("interpolation", "bspline")
    at_start = registration_score(captured, reference, start, 900.0, **same)
    assert bool((found.score.double() >= at_start).all())
    reported = registration_score(captured, reference, found.pose, 900.0, weights_at=start, **same)
    torch.testing.assert_close(found.score, reported, rtol=1e-9, atol=0)
    # A maximum: no move of 0.02 cells along x or y scores higher (a bilinear map's score has kinks on whole cells,
    # where its gradient need not vanish).
    for axis in (0, 1):
        for sign in (-1.0, 1.0):
            moved = found.pose.clone()
            moved[:, axis] += sign * 0.02
            nearby = registration_score(captured, reference, moved, 900.0, weights_at=start, **same)
            assert bool((nearby <= found.score.double() + 1e-9).all()), (axis, sign, nearby - found.score)
    if options.get("interpolation", "bspline") == "bspline":  # smooth: the gradient vanishes there
        pose = found.pose.clone().requires_grad_(True)
        (gradient,) = torch.autograd.grad(
            registration_score(captured, reference, pose, 900.0, weights_at=start, **same).sum(), pose
        )
        moved = start.clone().requires_grad_(True)
        (first,) = torch.autograd.grad(
            registration_score(captured, reference, moved, 900.0, weights_at=start, **same).sum(), moved
        )
        assert float(gradient[:, :2].abs().max()) < 0.05 * float(first[1:, :2].abs().max())  # steps below 1e-3 cells


def test_every_step_raises_the_score_with_the_shrunk_responses_pull():
    # Stopped after k steps, each image's score never falls as k grows: a step is taken only where the score (the
    # fit's misfit and the shrunk response's pull toward a line) rises. Mutation killed: steps accepted where the
    # residuals' sum of squares alone falls (5 falls over these 16 images).
    from skimage import data

    photo = torch.from_numpy(data.camera().astype(np.float64))
    for seed in range(2):
        generator = torch.Generator().manual_seed(seed)
        top, left = (int(torch.randint(0, 512 - 240, (1,), generator=generator)) for _ in range(2))
        moves = torch.randint(-5, 6, (8, 2), generator=generator).tolist()
        reference = F.avg_pool2d(photo[top : top + 240, left : left + 240][None, None], 3)
        cuts = [photo[top + 48 + y : top + 192 + y, left + 48 + x : left + 192 + x] for x, y in moves]
        captured = F.avg_pool2d(torch.stack(cuts)[:, None], 3)
        captured = (captured + 30 * torch.randn(captured.shape, generator=generator, dtype=torch.float64)).clamp(0, 256)
        start = torch.tensor([[40 + round(x / 3), 40 + round(y / 3), 0.0] for x, y in moves], dtype=torch.float64)
        scores = [
            register(captured, reference, 900.0, pose=start, iterations=steps, tolerance=1e-9).score
            for steps in range(1, 9)
        ]
        for fewer, more in itertools.pairwise(scores):
            assert bool((more >= fewer - 1e-12).all())


def test_a_map_too_large_for_its_interpolation_table_is_refused_before_allocating(generator):
    # 16 coefficients a cell for the B-spline (and its prefilter's spectrum), 4 for bilinear: one budget, two answers.
    from enmi_torch.utils.budget import MemoryBudgetError, memory_budget

    captured, reference, pose = _inputs(generator)  # a 64 x 64 map
    with memory_budget(64 * 64 * 60 * 8):
        with pytest.raises(MemoryBudgetError, match=r"interpolation='bspline' needs about .* crop the map"):
            register(captured, reference, 1.0, pose=pose)
        with pytest.raises(MemoryBudgetError, match=r"interpolation='bspline' needs about"):
            warp_reference(reference, pose, (16, 16))
        register(captured, reference, 1.0, pose=pose, interpolation="bilinear")
