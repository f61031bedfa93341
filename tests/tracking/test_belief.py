"""The belief: initial Gaussian, motion step, Bayes update, mismatch mixing, pose read-out, bad inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _tracking import cut, map_move, texture

from enmi_torch.tracking import Belief, TrackerSettings, belief_pose, initial_belief, predict, track_step, update
from enmi_torch.tracking.belief import mixed_with_mismatch
from enmi_torch.utils.budget import MemoryBudgetError


@pytest.mark.parametrize("yaw", [0.0, 30.0, -75.0])
def test_predict_conserves_probability_and_moves_by_the_odometry(yaw):
    belief = initial_belief(torch.tensor([[40.0, 30.0, yaw]]), shifts=(6, 9), yaw_bins=1, std=(1.0, 0.7, 1.0))
    before, _ = belief_pose(belief._replace(log_prob=belief.log_prob - 50))  # moments: no peak holds half the mass
    odometry = torch.tensor([[2.3, -1.6, 0.0]], dtype=torch.float64)
    moved = predict(belief, odometry, (0.4, 0.2, 0.0))
    assert float(moved.log_prob.exp().sum()) == pytest.approx(1.0, abs=1e-9)
    weights = moved.log_prob.exp()[0, 0]
    rows, cols = torch.meshgrid(*(torch.arange(size, dtype=torch.float64) for size in weights.shape), indexing="ij")
    mean_x = float((weights * (cols - 9 + moved.center[0, 1])).sum())
    mean_y = float((weights * (rows - 6 + moved.center[0, 0])).sum())
    step_x, step_y = map_move(yaw, 2.3, -1.6)
    assert mean_x == pytest.approx(float(before[0, 0]) + step_x, abs=1e-6)
    assert mean_y == pytest.approx(float(before[0, 1]) + step_y, abs=1e-6)
    # The window follows the belief: its middle cell is the rounded predicted mean.
    assert moved.center[0].tolist() == [round(mean_y), round(mean_x)]


def test_predict_moves_each_yaw_bin_by_its_own_heading_and_spreads_by_the_noise():
    log_prob = torch.full((1, 3, 11, 15), -math.inf, dtype=torch.float64)
    log_prob[0, 0, 5, 7] = log_prob[0, 2, 5, 7] = math.log(0.5)  # yaw 10 and 50 degrees, same cell
    belief = Belief(log_prob, torch.tensor([[50, 60]]), torch.tensor([30.0], dtype=torch.float64), 20.0)
    moved = predict(belief, torch.tensor([[0.0, -3.0, 0.0]], dtype=torch.float64), (0.0, 0.0, 0.0))
    for source, yaw in ((0, 10.0), (2, 50.0)):
        plane = moved.log_prob.exp()[0, source]
        rows, cols = torch.meshgrid(*(torch.arange(size, dtype=torch.float64) for size in plane.shape), indexing="ij")
        mass = float(plane.sum())
        x = float((plane * (cols - 7 + moved.center[0, 1])).sum()) / mass
        y = float((plane * (rows - 5 + moved.center[0, 0])).sum()) / mass
        step_x, step_y = map_move(yaw, 0.0, -3.0)
        assert mass == pytest.approx(0.5, abs=1e-12)
        assert (x, y) == pytest.approx((60 + step_x, 50 + step_y), abs=1e-9)
    # Noise: the spread along the image's columns grows by du's variance (a yaw-0 belief on one cell).
    log_prob = torch.full((1, 1, 21, 21), -math.inf, dtype=torch.float64)
    log_prob[0, 0, 10, 10] = 0.0
    still = Belief(log_prob, torch.tensor([[50, 60]]), torch.zeros(1, dtype=torch.float64), 1.0)
    spread = predict(still, torch.zeros(1, 3, dtype=torch.float64), (2.0, 1.0, 0.0)).log_prob.exp()[0, 0]
    offsets = torch.arange(-10.0, 11.0, dtype=torch.float64)
    assert float((spread.sum(0) * offsets.square()).sum()) == pytest.approx(4.0, rel=0.02)
    assert float((spread.sum(1) * offsets.square()).sum()) == pytest.approx(1.0, rel=0.02)


def test_predict_moves_the_yaw_by_the_odometry():
    belief = initial_belief(torch.tensor([[0.0, 0.0, 2.0]]), shifts=2, yaw_bins=7, yaw_step=2.0, std=(1.0, 1.0, 2.0))
    weights = belief.log_prob.exp()
    before = float((weights.sum((2, 3)) * belief.yaws()).sum())
    moved = predict(belief, torch.tensor([[0.0, 0.0, 1.3]], dtype=torch.float64), (0.0, 0.0, 0.0))
    weights = moved.log_prob.exp()
    after = float((weights.sum((2, 3)) * moved.yaws()).sum()) / float(weights.sum())
    assert float(weights.sum()) > 0.98  # a little mass leaves the seven bins
    assert after == pytest.approx(before + 1.3, abs=0.05)


def test_update_is_bayes_rule_and_ignores_left_out_candidates():
    belief = initial_belief(torch.zeros(2, 3), shifts=(1, 2), yaw_bins=3, std=(1.0, 2.0, 1.0))
    likelihood = torch.randn(2, 3, 3, 5, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    posterior = update(belief, likelihood).log_prob.exp()
    expected = (belief.log_prob + likelihood).exp()
    torch.testing.assert_close(posterior, expected / expected.sum((1, 2, 3), keepdim=True))
    likelihood[0, 0, 0, 0] = -math.inf
    assert bool(torch.isfinite(update(belief, likelihood).log_prob).all())


def test_belief_pose_refines_below_a_cell_and_reports_a_laplace_covariance():
    belief = initial_belief(torch.tensor([[20.0, 10.0, 0.0]]), shifts=(3, 4), yaw_bins=3)
    x, y = torch.meshgrid(torch.arange(-4.0, 5.0), torch.arange(-3.0, 4.0), indexing="xy")
    true_x, true_y, curvature = 0.3, -0.2, 8.0
    log_prob = (
        -0.5 * curvature * ((x - true_x) ** 2 + (y - true_y) ** 2) + torch.tensor([-9.0, 0.0, -9.0])[:, None, None]
    )
    pose, covariance = belief_pose(belief._replace(log_prob=log_prob[None].double()))
    assert pose[0, :2].tolist() == pytest.approx([20.3, 9.8], abs=1e-6)
    assert covariance[0, 0, 0] == pytest.approx(1 / curvature)
    assert covariance[0, 1, 1] == pytest.approx(1 / curvature)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("probability", [0.01, 0.3])
def test_mixed_with_mismatch_is_the_two_component_mixture_per_sample(dtype, probability):
    # Two samples whose peaks differ by 40 nats on a non-square grid: each is mixed relative to its own best cell.
    generator = torch.Generator().manual_seed(1)
    log_likelihood = (torch.randn(2, 3, 4, 5, generator=generator, dtype=torch.float64) * 6).to(dtype)
    log_likelihood[1] += 40.0
    log_likelihood[0, 2, 3, 4] = -math.inf  # a left-out candidate: the sample's smallest finite value
    mixed = mixed_with_mismatch(log_likelihood, probability)
    values = log_likelihood.double().numpy()
    for sample in range(2):
        finite = values[sample][np.isfinite(values[sample])]
        for index in np.ndindex(3, 4, 5):
            value = values[sample][index] if np.isfinite(values[sample][index]) else finite.min()
            expected = math.log((1 - probability) * math.exp(value - finite.max()) + probability)
            assert float(mixed[sample][index]) == pytest.approx(expected, abs=1e-9)
    spread = mixed.flatten(1).amax(1) - mixed.flatten(1).amin(1)
    assert bool((spread <= math.log(1 / probability) + 1e-9).all())  # one frame: at most log(1/p) nats
    assert mixed.dtype == torch.float64
    plain = mixed_with_mismatch(log_likelihood, 0)  # no mismatch: the likelihood relative to its best cell
    floored = torch.where(
        torch.isfinite(log_likelihood), log_likelihood, log_likelihood[0][torch.isfinite(log_likelihood[0])].min()
    )
    torch.testing.assert_close(plain, (floored - floored.flatten(1).amax(1)[:, None, None, None]).double())


@pytest.mark.parametrize("probability", [-0.1, 1.0, 1, math.nan, True, "0.05", None])
def test_mismatch_probability_outside_zero_to_one_is_refused_by_name(generator, probability):
    with pytest.raises(ValueError, match=r"mismatch_probability must be a number in \[0, 1\), got"):
        mixed_with_mismatch(torch.zeros(1, 1, 3, 3), probability)
    reference = texture(generator, (60, 90)).float()
    belief = initial_belief(torch.tensor([[45.0, 30.0, 0.0]]), shifts=3, yaw_bins=1)
    with pytest.raises(ValueError, match="mismatch_probability"):
        settings = TrackerSettings(mismatch_probability=probability)
        track_step(belief, cut(reference, 45, 30), reference, torch.zeros(1, 3), 1.0, settings=settings)


@pytest.mark.parametrize(
    ("noise", "yaw_step", "message"),
    [
        ((1e3, 1e3, 0.1), 1.0, r"noise 1e\+03 cells .* needs about 6.2 GiB for the float64 blur kernels"),
        ((0.5, 0.5, 0.5), 1e-12, r"5e\+11 yaw bins \(yaw_step=1e-12\) needs about .* TiB"),
    ],
)
def test_predict_refuses_blur_kernels_over_the_memory_budget_before_allocating(noise, yaw_step, message):
    belief = initial_belief(torch.zeros(1, 3), shifts=8, yaw_bins=5, yaw_step=yaw_step, std=(1.0, 1.0, 1.0))
    with pytest.raises(MemoryBudgetError, match=message):
        predict(belief, torch.tensor([[1.0, 0.0, 0.0]]), noise)


def test_update_refuses_a_positive_infinite_log_likelihood_instead_of_taking_it_for_the_weakest_cell():
    belief = initial_belief(torch.zeros(1, 3), shifts=1, yaw_bins=1)
    likelihood = torch.zeros(1, 1, 3, 3)
    likelihood[0, 0, 1, 1] = math.inf
    with pytest.raises(ValueError, match=r"log_likelihood must be finite, -inf or NaN .* got 1 cell\(s\) of \+inf"):
        update(belief, likelihood)


def test_the_initial_gaussian_belief_is_the_product_of_its_three_axes():
    pose = torch.tensor([[10.3, 20.6, 3.4]], dtype=torch.float64)
    std = (0.8, 1.7, 2.5)  # unequal on every axis: a swapped or inverted one fails
    belief = initial_belief(pose, shifts=(2, 3), yaw_bins=3, yaw_step=2.0, std=std)
    yaws = torch.tensor([1.4, 3.4, 5.4], dtype=torch.float64)[:, None, None]
    rows = torch.arange(19.0, 24.0, dtype=torch.float64)[None, :, None]  # centre row 21 = round(20.6)
    cols = torch.arange(7.0, 14.0, dtype=torch.float64)[None, None, :]  # centre column 10
    log_density = -0.5 * (((cols - 10.3) / 0.8) ** 2 + ((rows - 20.6) / 1.7) ** 2 + ((yaws - 3.4) / 2.5) ** 2)
    expected = log_density - torch.logsumexp(log_density.flatten(), 0)
    torch.testing.assert_close(belief.log_prob[0], expected)


def test_belief_pose_refines_up_to_half_a_bin_inside_the_window_and_not_at_its_edge():
    belief = initial_belief(torch.tensor([[5.0, 7.0, 0.0]]), shifts=2, yaw_bins=1)
    ruled_out = torch.full((1, 1, 5, 5), -80.0, dtype=torch.float64)
    near = ruled_out.clone()
    near[0, 0, 2, 1:4] = torch.tensor([-1.0, 0.0, -9.0])  # vertex 0.4 bins left of column 5
    pose, _ = belief_pose(belief._replace(log_prob=near))
    assert pose[0, 0].item() == pytest.approx(4.6, abs=1e-12) and pose[0, 1].item() == pytest.approx(7.0, abs=1e-12)
    edge = ruled_out.clone()
    edge[0, 0, 2, 3:5] = torch.tensor([-3.0, 0.0])  # the peak on the window's last column: no parabola through it
    pose, _ = belief_pose(belief._replace(log_prob=edge))
    assert pose[0, 0].item() == pytest.approx(7.0, abs=1e-12)


def test_a_flat_beliefs_covariance_is_its_second_moment_plus_a_bin_spread_uniformly():
    belief = initial_belief(torch.tensor([[5.0, 7.0, 0.0]]), shifts=(1, 2), yaw_bins=3, yaw_step=2.0)
    _, covariance = belief_pose(belief)  # flat: no bin holds half the mass
    # x over -2..2 cells: variance 2 + 1/12; y over -1..1: 2/3 + 1/12; yaw over -2, 0, 2 degrees: 8/3 + 4/12.
    expected = torch.diag(torch.tensor([2 + 1 / 12, 2 / 3 + 1 / 12, 8 / 3 + 4 / 12], dtype=torch.float64))
    torch.testing.assert_close(covariance[0], expected)


def test_the_belief_budget_counts_every_cell_of_the_window():
    from enmi_torch.utils.budget import format_bytes, memory_budget

    expected = 8 * 8 * 4 * 3 * (2 * 300 + 1) * (2 * 200 + 1)  # 8 float64 copies of (4, 3, 601, 401)
    with memory_budget(1000), pytest.raises(MemoryBudgetError, match=rf"needs about {format_bytes(expected)} "):
        initial_belief(torch.zeros(4, 3), shifts=(300, 200), yaw_bins=3)


def _bad_call(case: str):
    belief = initial_belief(torch.zeros(1, 3), shifts=2, yaw_bins=1)
    odometry = torch.zeros(1, 3)
    calls = {
        "even yaw bins": lambda: initial_belief(torch.zeros(1, 3), yaw_bins=4),
        "pose shape": lambda: initial_belief(torch.zeros(3)),
        "pose dtype": lambda: initial_belief(torch.zeros(1, 3, dtype=torch.int64)),
        "negative shifts": lambda: initial_belief(torch.zeros(1, 3), shifts=-1),
        "yaw step": lambda: initial_belief(torch.zeros(1, 3), yaw_step=0.0),
        "std": lambda: initial_belief(torch.zeros(1, 3), std=(1.0, 1.0)),
        "odometry shape": lambda: predict(belief, torch.zeros(2, 3), (0.1, 0.1, 0.1)),
        "odometry nan": lambda: predict(belief, torch.full((1, 3), math.nan), (0.1, 0.1, 0.1)),
        "negative noise": lambda: predict(belief, odometry, (0.1, -0.1, 0.1)),
        "not a belief": lambda: predict((1, 2), odometry, (0.1, 0.1, 0.1)),
        "likelihood shape": lambda: update(belief, torch.zeros(1, 1, 5, 4)),
    }
    return calls[case]


@pytest.mark.parametrize(
    ("case", "error", "match"),
    [
        ("even yaw bins", ValueError, "yaw_bins must be odd"),
        ("pose shape", ValueError, r"pose must have shape \(B, 3\)"),
        ("pose dtype", TypeError, "pose must be a floating-point tensor"),
        ("negative shifts", ValueError, "shifts must be an int >= 0"),
        ("yaw step", ValueError, "yaw_step must be a finite number > 0"),
        ("std", ValueError, "std must be three numbers"),
        ("odometry shape", ValueError, r"odometry must have shape \(1, 3\)"),
        ("odometry nan", ValueError, "odometry must be finite"),
        ("negative noise", ValueError, "noise must be three standard deviations >= 0"),
        ("not a belief", TypeError, "belief must be a Belief"),
        ("likelihood shape", ValueError, "log_likelihood must have the belief's shape"),
    ],
)
def test_bad_inputs_raise_naming_the_argument(case, error, match):
    with pytest.raises(error, match=match):
        _bad_call(case)()
