"""Registration by Gauss-Newton through a score: exact recovery, gradients, pixels off the map, batching, refusals."""

from __future__ import annotations

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
    reference = _map(generator)
    pose = torch.tensor([[40.3, 31.7, 23.0], [52.0, 40.0, -60.0]], dtype=torch.float64)
    warped, valid = warp_reference(reference, pose, SHAPE)
    transform = Localization(pose, *(torch.zeros(2),) * 5).local_to_map((0, 0), SHAPE)
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
    assert bool(valid.all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("score", [ECR(bins=16), ECR(response="linear"), NCC()], ids=["ecr", "ecr-linear", "ncc"])
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
    with pytest.raises(ValueError, match=r"score must be ECR or NCC for register .* got .nmi."):
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
    options = {"shifts": 5, "center": (40, 44), "yaws": [-2.0, -1.0, 0.0, 1.0, 2.0]}
    grid = localize(captured, reference.float(), 1.0, **options)
    refined = localize(captured, reference.float(), 1.0, refine=True, **options)
    expected = [0.3, 0.6, 1.3]
    assert refined.pose[0].tolist() == pytest.approx(expected, abs=2e-3)
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
