"""Conventions a single-point change would break unnoticed (issue 23, item 7): each test fails on one mutation."""

import numpy as np
import pytest
import torch
from skimage import data

from enmi_torch.binning import likelihood_weights, likelihood_weights_vjp, min_variance
from enmi_torch.localization.peak import _quadratic_fit, _quadratic_peak
from enmi_torch.localization.search import localize

RANGE = (0.0, 256.0)


@pytest.mark.parametrize("kernel", ["mass", "density", "truncated"])
def test_the_variance_gradient_is_zero_where_the_variance_is_clamped(kernel):
    # Mutation killed: likelihood_weights_vjp's density branch returning grad_variance without zeroing it where the
    # variance was clamped to min_variance (autograd through the clamp gives 0 there).
    floor = min_variance(16, RANGE)
    generator = torch.Generator().manual_seed(0)
    # Values within a few sigma^2 / bin width of a bin edge: there a variance at the floor still moves weight between
    # the two bins, so the unclamped derivative is far from zero.
    edges = 16.0 * torch.randint(1, 16, (48,), generator=generator, dtype=torch.float64)
    values = (edges + floor / 16 * torch.linspace(-3, 3, 48, dtype=torch.float64)).requires_grad_()
    variance = floor * torch.logspace(-3, 3, 48, dtype=torch.float64)[torch.randperm(48, generator=generator)]
    variance.requires_grad_()  # half below the floor
    upstream = torch.randn(48, 16, generator=generator, dtype=torch.float64)
    weights = likelihood_weights(values, variance, 16, RANGE, kernel)
    expected = torch.autograd.grad(weights, (values, variance), upstream)
    actual = likelihood_weights_vjp(values.detach(), variance.detach(), upstream, 16, RANGE, kernel)
    clamped = variance.detach() < floor
    assert clamped.sum() >= 20
    assert bool((actual[1][clamped] == 0).all())
    for got, want in zip(actual, expected, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-2, atol=1e-12)  # derivatives up to 1e16, cancellations


def test_a_vertex_beyond_half_a_cell_is_refitted_on_the_neighbouring_cell():
    # Mutation killed: _quadratic_peak accepting the first fit up to 1.0 cell (instead of 0.5) before re-centring.
    rows, cols = torch.meshgrid(torch.arange(9.0).double(), torch.arange(9.0).double(), indexing="ij")
    plane = torch.exp(-((cols - 4.7) ** 2 + (rows - 4.0) ** 2) / (2 * 1.2**2))  # a Gaussian peak, not a quadratic
    first, _ = _quadratic_fit(plane, 4, 4)
    assert 0.5 < float(first[0]) <= 1.0  # the fit around cell (4, 4) points past half a cell
    refit, refit_covariance = _quadratic_fit(plane, 4, 5)
    offset, covariance = _quadratic_peak(plane, 4, 4)
    torch.testing.assert_close(offset, refit + torch.tensor([1.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(covariance, refit_covariance)
    assert abs(float(offset[0]) - 0.7) < abs(float(first[0]) - 0.7)  # and closer to the true peak


def test_the_default_center_is_the_map_centre_row_then_column_on_a_non_square_map():
    # Mutation killed: localize's default center (Hm // 2, Wm // 2) swapped to (Wm // 2, Hm // 2).
    section = torch.from_numpy(data.gravel()[100:140, 150:214].astype(np.float64)).reshape(1, 1, 40, 64)
    height, width = section.shape[-2:]
    row, col = height // 2, width // 2
    captured = section[..., row - 8 : row + 8, col - 8 : col + 8].clone()
    default = localize(captured, section, score="ncc", shifts=3)
    explicit = localize(captured, section, score="ncc", shifts=3, around=(col, row))
    assert default.pose[0].tolist() == pytest.approx([col, row, 0.0], abs=0.05)  # found where it was cut
    assert default.shift[0].tolist() == pytest.approx([0.0, 0.0], abs=0.05)
    torch.testing.assert_close(default.pose, explicit.pose)
    torch.testing.assert_close(default.score, explicit.score)


def _smooth_map(shape: tuple[int, int]) -> torch.Tensor:
    """A smooth random texture ``(1, 1, *shape)`` in grey levels (peaks a few cells wide), float64."""
    generator = torch.Generator().manual_seed(7)
    noise = torch.rand(1, 1, shape[0] + 4, shape[1] + 4, generator=generator, dtype=torch.float64)
    smooth = torch.nn.functional.avg_pool2d(torch.nn.functional.avg_pool2d(noise, 3, 1), 3, 1)
    return (smooth - smooth.min()) / (smooth.max() - smooth.min()) * 250 + 2


def test_the_pose_localize_returns_is_what_register_and_tracker_start_take():
    # Mutations killed: localize returning the pose relative to around (the former (dx, dy, yaw)); around read as
    # (row, col); register's or the belief's x and y swapped. A 70 x 150 map, the prior far from its centre (75, 35),
    # the truth 4.4 columns right of and 3.3 rows above it, a 24 x 32 captured image.
    from enmi_torch import ECR, Tracker, TrackerSettings, register
    from enmi_torch.registration import warp_reference

    reference = _smooth_map((70, 150))
    truth = torch.tensor([[122.4, 17.7, 1.0]], dtype=torch.float64)
    noise = torch.randn(1, 1, 24, 32, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    captured = warp_reference(reference, truth, (24, 32))[0] + 0.5 * noise
    options = {"score": ECR(bins=16), "shifts": (5, 6), "around": (118, 21), "yaws": [0.0, 1.0, 2.0]}
    found = localize(captured, reference, 0.25, **options)
    assert found.pose[0, :2].tolist() == pytest.approx(truth[0, :2].tolist(), abs=0.3)
    assert abs(float(found.yaw[0]) - 1.0) <= 1.0  # nearest-neighbour turns of a small image: within a yaw step
    assert found.shift[0].tolist() == pytest.approx([4.4, -3.3], abs=0.3)
    refined = register(captured, reference, 0.25, pose=found.pose, score=ECR(bins=16))
    assert refined.pose[0].tolist() == pytest.approx(truth[0].tolist(), abs=0.02)
    torch.testing.assert_close(localize(captured, reference, 0.25, refine=True, **options).pose, refined.pose)
    tracker = Tracker(reference, score=ECR(bins=16), shifts=(3, 4), yaw_bins=3, settings=TrackerSettings())
    tracker.start(found.pose)
    assert tracker.belief.center.tolist() == [[18, 122]]  # (row, col) of the window: y, x rounded
    step = torch.tensor([[2.0, -1.0, 0.0]], dtype=torch.float64)  # two cells along the image's columns, one up
    turn = torch.deg2rad(-truth[0, 2])  # the image's axes on the map at yaw 1: (cos a du + sin a dv, ...), a = -yaw
    move = [turn.cos() * 2.0 + turn.sin() * -1.0, -turn.sin() * 2.0 + turn.cos() * -1.0, 0.0]
    moved = truth + torch.tensor([move], dtype=torch.float64)
    frame = warp_reference(reference, moved, (24, 32))[0] + 0.5 * noise
    output = tracker(frame, step, 0.25)
    assert bool(output.healthy[0])
    assert output.pose[0, :2].tolist() == pytest.approx(moved[0, :2].tolist(), abs=0.5)
