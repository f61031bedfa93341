"""The histogram filter: motion step, update, pose read-out, tracking, relocalization, calibration, bad inputs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from enmi_torch import (
    ECR,
    NMI,
    ConstantVariance,
    Localization,
    MemoryBudgetError,
    NoCandidateError,
    as_score,
    localize,
    warp_reference,
)
from enmi_torch.tracking import (
    Belief,
    Calibration,
    Tracker,
    TrackerSettings,
    belief_pose,
    calibrate_temperature,
    grid_temperature,
    initial_belief,
    predict,
    track_step,
    update,
)
from enmi_torch.tracking.belief import grid_poses, mixed_with_mismatch, normalized

FRAME = (24, 32)  # non-square frames: a swapped axis fails


def _map_move(yaw: float, du: float, dv: float) -> tuple[float, float]:
    """The map move of an image-axes increment at ``yaw``, from Localization.local_to_map's linear part."""
    transform = Localization(torch.tensor([[0.0, 0.0, yaw]], dtype=torch.float64), *(torch.zeros(1),) * 5).local_to_map(
        (0, 0), (5, 5)
    )
    move = transform[0, :2, :2].double() @ torch.tensor([du, dv], dtype=torch.float64)
    return float(move[0]), float(move[1])


def _texture(generator: torch.Generator, shape: tuple[int, int]) -> torch.Tensor:
    """A smooth random texture in grey levels: peaks a few cells wide, like a road surface."""
    noise = torch.rand(1, 1, *shape, generator=generator, dtype=torch.float64)
    smooth = torch.nn.functional.avg_pool2d(noise, 3, 1, 1, count_include_pad=False)
    return (smooth - smooth.min()) / (smooth.max() - smooth.min()) * 255


def _cut(reference: torch.Tensor, x: int, y: int) -> torch.Tensor:
    """The frame whose centre pixel ``(h // 2, w // 2)`` lies on map cell ``(y, x)`` at yaw 0."""
    height, width = FRAME
    return reference[..., y - height // 2 : y - height // 2 + height, x - width // 2 : x - width // 2 + width]


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
    step_x, step_y = _map_move(yaw, 2.3, -1.6)
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
        step_x, step_y = _map_move(yaw, 0.0, -3.0)
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
    reference = _texture(generator, (60, 90)).float()
    belief = initial_belief(torch.tensor([[45.0, 30.0, 0.0]]), shifts=3, yaw_bins=1)
    with pytest.raises(ValueError, match="mismatch_probability"):
        settings = TrackerSettings(mismatch_probability=probability)
        track_step(belief, _cut(reference, 45, 30), reference, torch.zeros(1, 3), 1.0, settings=settings)


def test_a_mismatch_probability_bounds_how_far_one_wrong_frame_moves_the_belief(generator):
    # The belief is sure of (45, 30); the frame is the map 3 cells right and 2 down, a sharp, clear wrong match.
    reference = _texture(generator, (60, 90)).float()
    belief = initial_belief(torch.tensor([[45.0, 30.0, 0.0]]), shifts=(4, 5), yaw_bins=1, std=(0.7, 0.7, 1.0))
    frame, odometry, noise = _cut(reference, 48, 32), torch.zeros(1, 3), (0.5, 0.5, 0.3)
    prior = predict(belief, odometry, noise).log_prob
    moves = {}
    for probability in (0.0, 0.05):
        settings = TrackerSettings(motion_noise=noise, mismatch_probability=probability)
        posterior, output, _ = track_step(
            belief, frame, reference, odometry, 1.0, score=ECR(bins=16), settings=settings
        )
        assert bool(output.healthy[0])  # the frame is used in full
        moved = (posterior.log_prob - prior).flatten()
        moves[probability] = float(moved.max() - moved.min())
    assert moves[0.0] > 2 * math.log(1 / 0.05)  # taken as it is, the frame moves the odds by more than the bound
    assert 1 < moves[0.05] <= math.log(1 / 0.05) + 1e-9  # mixed: still used, by at most log(1/p) nats
    unmixed, _, _ = track_step(
        belief, frame, reference, odometry, 1.0, score=ECR(bins=16), settings=TrackerSettings(motion_noise=noise)
    )
    zero_settings = TrackerSettings(motion_noise=noise, mismatch_probability=0)
    zero, _, _ = track_step(belief, frame, reference, odometry, 1.0, score=ECR(bins=16), settings=zero_settings)
    assert torch.equal(unmixed.log_prob, zero.log_prob)  # 0, the default: the likelihood as it is


@pytest.mark.parametrize(("temperature", "tolerance"), [(1.0, 1e-6), ("auto", 0.01)])
def test_noiseless_drive_is_tracked_exactly(generator, temperature, tolerance):
    # With the raw log-likelihood (temperature 1, the default before "auto") the pose is the cell itself; the default
    # flattens it to one bin's spread, which leaves the mean within a hundredth of a cell.
    reference = _texture(generator, (96, 200))
    tracker = Tracker(
        reference.float(),
        score=ECR(bins=16, response="binned"),  # the tracker's response (default_score says why)
        shifts=(4, 5),
        yaw_bins=3,
        settings=TrackerSettings(motion_noise=(0.5, 0.5, 0.3), temperature=temperature),
    )
    tracker.start(torch.tensor([[40.0, 50.0, 0.0]]))
    x, y = 40, 50
    for step in range(12):
        du, dv = (3, 0) if step % 3 else (2, 1)  # unequal moves along columns and rows
        x, y = x + du, y + dv
        output = tracker(_cut(reference, x, y).float(), torch.tensor([[float(du), float(dv), 0.0]]), 1.0)
        assert output.pose[0, :2].tolist() == pytest.approx([x, y], abs=tolerance)
        assert float(output.pose[0, 2]) == pytest.approx(0.0, abs=max(tolerance, 1e-3))  # nearest-neighbour turns
        assert bool(output.healthy[0]) and not bool(output.lost[0])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_grid_temperature_caps_each_axis_at_one_bin(dtype):
    # Curvatures 30 (yaw), 6 (rows) and 96 (columns) per bin^2 on a non-square grid whose peak is off-centre: the
    # sharpest axis, the columns, sets 1 + 96 / 12 = 9; a swapped or missed axis gives another number.
    yaw, rows, cols = torch.meshgrid(torch.arange(3.0) - 1, torch.arange(7.0) - 2, torch.arange(9.0) - 5, indexing="ij")
    sharp = -0.5 * (30.0 * yaw**2 + 6.0 * rows**2 + 96.0 * cols**2)
    flat = torch.zeros(3, 7, 9)
    dipped = 0.5 * 96.0 * cols**2  # the maximum at a border, the curvature upwards: counts zero
    log_likelihood = torch.stack([sharp, flat, dipped]).to(dtype)
    assert grid_temperature(log_likelihood).tolist() == pytest.approx([9.0, 1.0, 1.0])
    assert grid_temperature(sharp[:, :, :2][None].to(dtype)).tolist() == pytest.approx([1 + 30.0 / 12])
    at_border = sharp[None, :, :, 1:].clone()  # the peak on the window's first column: read one bin inwards
    assert grid_temperature(at_border.to(dtype)).tolist() == pytest.approx([9.0])
    sharp[0, 0, 0] = -math.inf  # a candidate left out: the smallest finite value, the peak's curvature unchanged
    assert grid_temperature(sharp[None].to(dtype)).tolist() == pytest.approx([9.0])


def test_a_window_without_candidates_raises_no_candidate_error(generator):
    reference = _texture(generator, (40, 60)).float()
    with pytest.raises(NoCandidateError, match="the search window lies off the map"):
        localize(_cut(reference, 30, 20), reference, 1.0, shifts=3, center=(20, 500))


def _edge_drive(generator, steps: int, frame_of, start_x: float = 45.0) -> list:
    reference = _texture(generator, (60, 90))
    settings = TrackerSettings(motion_noise=(0.3, 0.3, 0.1), patience=2, relocalize_shifts=6, coarse_factor=2)
    tracker = Tracker(reference.float(), settings=settings, score=ECR(bins=16), shifts=3, yaw_bins=1)
    tracker.start(torch.tensor([[start_x, 30.0, 0.0]]))
    return [frame_of(tracker, reference, step) for step in range(steps)]


def test_a_fully_masked_frame_coasts_on_the_odometry(generator):
    def frame_of(tracker, reference, step):
        before = tracker.belief
        mask = torch.full((1, 1, *FRAME), step != 2)  # the third frame sees nothing
        output = tracker(_cut(reference, 45 + 2 * (step + 1), 30).float(), torch.tensor([[2.0, 0.0, 0.0]]), 1.0, mask)
        return before, output

    outputs = _edge_drive(generator, 5, frame_of)
    before, masked = outputs[2]
    assert not bool(masked.healthy[0]) and math.isnan(float(masked.score[0])) and math.isnan(float(masked.peak_z[0]))
    coasted, _ = belief_pose(predict(before, torch.tensor([[2.0, 0.0, 0.0]]), (0.3, 0.3, 0.1)))
    torch.testing.assert_close(masked.pose, coasted)  # the prediction alone
    _, last = outputs[-1]
    assert bool(last.healthy[0]) and not bool(last.lost[0])
    assert last.pose[0, :2].tolist() == pytest.approx([55.0, 30.0], abs=0.05)


def _position_variance(belief: Belief) -> torch.Tensor:
    """The ``(x, y)`` variance of a belief's bins, from their moments (no read-out rule in between)."""
    weights = normalized(belief.log_prob).exp()
    x, y, _ = grid_poses(belief)
    spread = []
    for values in (x.expand_as(weights), y.expand_as(weights)):
        mean = (weights * values).sum()
        spread.append((weights * (values - mean).square()).sum())
    return torch.stack(spread)


@pytest.mark.parametrize(
    ("coasting", "growth"), [(None, lambda k: k), ("linear", lambda k: k * k), ("random_walk", lambda k: k)]
)
def test_a_coasting_belief_widens_as_a_random_walk_by_default_or_as_a_bias(generator, coasting, growth):
    # Frames that see nothing: "random_walk" (the default) adds sigma^2 a frame; "linear" adds (2k + 1) sigma^2 after k
    # coasted frames, k^2 sigma^2 in all, a constant bias's spread. Unequal noise along u (x, the map's columns
    # at yaw 0) and v (y, rows) catches swapped axes.
    reference = _texture(generator, (80, 120)).float()
    settings = TrackerSettings(motion_noise=(1.0, 0.6, 0.1))
    if coasting is not None:  # None: the default
        settings = settings.replace(coasting=coasting)
    tracker = Tracker(reference, settings=settings, score=ECR(bins=16), shifts=20, yaw_bins=1)
    tracker.start(torch.tensor([[60.0, 40.0, 0.0]]), std=(1.5, 1.5, 0.1))
    start_variance = _position_variance(tracker.belief)
    blind = torch.zeros(1, 1, *FRAME, dtype=torch.bool)
    for frames in range(1, 6):
        output = tracker(_cut(reference, 60, 40).float(), torch.zeros(1, 3), 1.0, blind)
        added = _position_variance(tracker.belief) - start_variance
        expected = growth(frames) * torch.tensor([1.0, 0.36], dtype=torch.float64)
        torch.testing.assert_close(added, expected, rtol=0.04, atol=0.0)  # a discrete Gaussian, cut at 20 cells
        assert not bool(output.healthy[0]) and bool(output.lost[0]) == (frames >= 2)


def test_odometry_off_the_map_is_lost_then_found_again_without_an_exception(generator):
    # The odometry claims a jump of 200 cells (off the 90-cell map) for three frames, then returns: the windows there
    # hold no candidate (NoCandidateError inside, caught), the filter coasts and says lost, and recovers when back.
    def frame_of(tracker, reference, step):
        jump = {1: 200.0, 4: -200.0}.get(step, 0.0)
        return tracker(_cut(reference, 45, 30).float(), torch.tensor([[jump, 0.0, 0.0]]), 1.0)

    outputs = _edge_drive(generator, 7, frame_of)
    assert [bool(output.healthy[0]) for output in outputs] == [True, False, False, False, True, True, True]
    assert [bool(output.lost[0]) for output in outputs] == [False, False, True, True, False, False, False]
    assert outputs[-1].pose[0, :2].tolist() == pytest.approx([45.0, 30.0], abs=0.05)


def test_a_belief_at_the_map_edge_keeps_tracking(generator):
    # The vehicle drives off the map's right edge: frames half off the map (their outer half masked) still match.
    def frame_of(tracker, reference, step):
        x = 76 + 2 * step
        padded = torch.nn.functional.pad(reference, (0, 40))
        valid = torch.nn.functional.pad(torch.ones_like(reference, dtype=torch.bool), (0, 40))
        output = tracker(_cut(padded, x, 30).float(), torch.tensor([[2.0, 0.0, 0.0]]), 1.0, _cut(valid, x, 30))
        return x, output

    outputs = _edge_drive(generator, 8, frame_of, start_x=74.0)
    for x, output in outputs:
        assert output.pose[0, :2].tolist() == pytest.approx([x, 30.0], abs=0.5)


def test_a_tracker_refines_each_used_frame_below_one_cell(generator):
    # Frames cut at sub-cell poses (bilinear): the belief stays on its cells, the refined pose finds the truth.
    reference = _texture(generator, (96, 200))
    tracker = Tracker(
        reference.float(),
        settings=TrackerSettings(motion_noise=(0.5, 0.5, 0.3), refine=True),
        score=ECR(bins=16),
        shifts=4,
        yaw_bins=3,
    )
    tracker.start(torch.tensor([[40.0, 50.0, 0.0]]))
    truth = torch.tensor([[40.0, 50.0, 0.0]], dtype=torch.float64)
    for _ in range(6):
        move = torch.tensor([[2.6, 0.3, 0.0]], dtype=torch.float64)
        truth = truth + move
        frame = warp_reference(reference, truth, FRAME)[0].float()
        output = tracker(frame, move.float(), 1.0)
        assert bool(output.healthy[0])
        assert output.refined[0].tolist() == pytest.approx(truth[0].tolist(), abs=5e-3)
    assert float((output.pose[0, :2].double() - truth[0, :2]).abs().max()) < 0.6  # the belief's own: one cell
    belief = initial_belief(torch.tensor([[40.0, 50.0, 0.0]]))
    with pytest.raises(ValueError, match="score must be ECR or NCC for register"):
        track_step(belief, frame, reference.float(), move.float(), settings=TrackerSettings(refine=True), score="nmi")


def test_a_kidnapped_vehicle_is_recovered_by_relocalization(generator):
    reference = _texture(generator, (120, 240))
    settings = TrackerSettings(motion_noise=(0.3, 0.3, 0.1), patience=2, relocalize_shifts=40, coarse_factor=2)
    tracker = Tracker(reference.float(), settings=settings, score=ECR(bins=16), shifts=4, yaw_bins=1)
    tracker.start(torch.tensor([[40.0, 60.0, 0.0]]))
    x, y, recovered_after, relocalized = 40, 60, None, []
    for step in range(16):
        x += 3
        if step == 5:
            x, y = x + 25, y - 12  # the vehicle is carried away; odometry reports the usual move
        output = tracker(_cut(reference, x, y).float(), torch.tensor([[3.0, 0.0, 0.0]]), 1.0)
        error = (output.pose[0, :2] - torch.tensor([x, y], dtype=torch.float64)).abs().max()
        if bool(output.relocalized[0]):
            relocalized.append(step)
            assert bool(output.healthy[0])  # a relocalized frame is a used match
            # The belief restarts from the frame's tempered likelihood: no sharper than one cell (variance 1 / 12).
            assert float(output.covariance[0, :2, :2].diagonal().min()) > 0.5 / 12, output.covariance
        if step >= 5 and recovered_after is None and float(error) < 1:
            recovered_after = step - 5
    assert len(relocalized) == 1 and relocalized[0] == 5 + recovered_after
    assert recovered_after is not None and recovered_after <= 2
    assert float(error) < 0.5


def test_a_lone_match_elsewhere_after_weak_frames_does_not_move_a_filter_that_was_right(generator):
    # Two frames without a match (noise), then one frame that matches another place (as a static occluder or a
    # repeated pattern can), then the vehicle's own frames again: one frame's best match over the wide window is no
    # reason to jump (it jumped 27 cells before the wide searches of two frames had to agree).
    reference = _texture(generator, (120, 240))
    settings = TrackerSettings(motion_noise=(0.3, 0.3, 0.1), patience=2, relocalize_shifts=40, coarse_factor=2)
    tracker = Tracker(reference.float(), settings=settings, score=ECR(bins=16), shifts=4, yaw_bins=1)
    tracker.start(torch.tensor([[40.0, 60.0, 0.0]]))
    x, y = 40, 60
    noise = torch.Generator().manual_seed(5)
    for step in range(12):
        x += 3
        frame = _cut(reference, x, y)
        if step in (5, 6):
            frame = torch.rand(frame.shape, generator=noise, dtype=frame.dtype) * 256
        if step == 7:
            frame = _cut(reference, x + 25, y - 12)
        output = tracker(frame.float(), torch.tensor([[3.0, 0.0, 0.0]]), 1.0)
        assert not bool(output.relocalized[0]), step
    assert float((output.pose[0, :2] - torch.tensor([x, y], dtype=torch.float64)).abs().max()) < 0.5
    assert bool(output.healthy[0]) and not bool(output.lost[0])


def test_a_weak_frame_whose_wide_search_lands_on_the_window_peak_is_used_without_a_jump(generator):
    # After clear frames (peak z ~60), noisy ones (z ~10) fall under z_drop times the recent matches' z: skipped. The
    # second such frame searches wide; its best match is the window's own peak, so the frame is used, no restart.
    reference = _texture(generator, (120, 240))
    settings = TrackerSettings(motion_noise=(0.3, 0.3, 0.1), patience=2, relocalize_shifts=40, coarse_factor=2)
    tracker = Tracker(reference.float(), settings=settings, score=ECR(bins=16), shifts=4, yaw_bins=1)
    tracker.start(torch.tensor([[40.0, 60.0, 0.0]]))
    x, noise, outputs = 40, torch.Generator().manual_seed(1), []
    for step in range(7):
        x += 3
        frame, variance = _cut(reference, x, 60), 1.0
        if step >= 5:
            frame, variance = frame + 100.0 * torch.randn(frame.shape, generator=noise, dtype=frame.dtype), 1e4
        outputs.append(tracker(frame.float(), torch.tensor([[3.0, 0.0, 0.0]]), variance))
    assert not bool(outputs[5].healthy[0]) and 3.0 <= float(outputs[5].peak_z[0]) < 0.3 * float(outputs[4].peak_z[0])
    assert bool(outputs[6].healthy[0]) and not bool(outputs[6].relocalized[0])
    assert float((outputs[6].pose[0, :2] - torch.tensor([x, 60.0], dtype=torch.float64)).abs().max()) < 0.1


def test_batched_vehicles_equal_one_at_a_time(generator):
    reference = _texture(generator, (80, 120)).float()
    starts = torch.tensor([[40.0, 30.0, 0.0], [70.0, 45.0, 0.0]])
    odometry = torch.tensor([[2.0, 1.0, 0.0], [-1.0, 2.0, 0.0]])
    frames = torch.cat([_cut(reference, 42, 31), _cut(reference, 69, 47)])
    # One variance map and one mask per vehicle (the second 4x noisier in its far half, the first blind in its left
    # third), sliced per vehicle by the searches.
    variance = torch.ones(2, 1, *frames.shape[-2:])
    variance[1, :, : frames.shape[-2] // 2] = 4.0
    mask = torch.ones(2, 1, *frames.shape[-2:], dtype=torch.bool)
    mask[0, :, :, : frames.shape[-1] // 3] = False
    batched = Tracker(reference, score=ECR(bins=16), shifts=3, yaw_bins=1)
    batched.start(starts)
    together = batched(frames, odometry, variance, mask)
    for vehicle in range(2):
        alone = Tracker(reference, score=ECR(bins=16), shifts=3, yaw_bins=1)
        alone.start(starts[vehicle : vehicle + 1])
        one = slice(vehicle, vehicle + 1)
        single = alone(frames[one], odometry[one], variance[one], mask[one])
        torch.testing.assert_close(together.pose[vehicle], single.pose[0])
        torch.testing.assert_close(together.covariance[vehicle], single.covariance[0])
        torch.testing.assert_close(together.score[vehicle], single.score[0])


def test_module_agrees_with_the_function(generator):
    reference = _texture(generator, (80, 120)).float()
    tracker = Tracker(reference, settings=TrackerSettings(temperature=0.01), score=NMI(bins=16), shifts=3, yaw_bins=3)
    tracker.start(torch.tensor([[60.0, 40.0, 0.0]]), std=(1.0, 1.0, 1.0))
    start = tracker.belief
    frame, odometry = _cut(reference, 62, 41), torch.tensor([[2.0, 1.0, 0.0]])
    output = tracker(frame, odometry)
    settings = TrackerSettings(temperature=0.01)
    belief, expected, health = track_step(
        start, frame, reference, odometry, None, score=NMI(bins=16), settings=settings
    )
    torch.testing.assert_close(output.pose, expected.pose)
    torch.testing.assert_close(tracker.belief.log_prob, belief.log_prob)
    assert health.weak_frames.tolist() == tracker.health.weak_frames.tolist()


def test_calibrate_temperature_recovers_the_scale_of_an_overconfident_likelihood():
    generator = torch.Generator().manual_seed(3)
    count, scale = 600, 8.0
    truth = torch.randint(3, 8, (count, 2), generator=generator).double()
    peaks = truth + torch.randn(count, 2, generator=generator, dtype=torch.float64)
    rows, cols = torch.meshgrid(torch.arange(11.0), torch.arange(11.0), indexing="ij")
    log_likelihood = -0.5 * scale * ((rows - peaks[:, :1, None]) ** 2 + (cols - peaks[:, 1:, None]) ** 2)
    index = torch.cat([truth, torch.zeros(count, 1, dtype=torch.float64)], 1)
    # The measured peaks scatter by 1 cell, the likelihood claims 1 / sqrt(8): the right temperature is near 8.
    assert calibrate_temperature(log_likelihood[:, None].double(), index) == pytest.approx(scale, rel=0.3)


def test_calibration_round_trips_through_json(tmp_path):
    calibration = Calibration("ecr", 123.5, 2.5)
    assert Calibration.load(calibration.save(tmp_path / "calibration.json")) == calibration
    (tmp_path / "bad.json").write_text('{"metric": "ecr"}')
    with pytest.raises(ValueError, match="needs keys"):
        Calibration.load(tmp_path / "bad.json")


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("[1, 2]", "must hold a JSON object .* got a list"),
        ("3", "must hold a JSON object .* got a number 3"),
        ("null", "must hold a JSON object .* got null"),
        ("[" * 100_000 + "]" * 100_000, "nests too deeply"),
        ("{not json", "is not readable JSON"),
        (
            '{"score": "ecr", "temperature": "2", "min_peak_z": 2.5}',
            "temperature must be a finite number, got a string",
        ),
        ('{"score": "ecr", "temperature": NaN, "min_peak_z": 2.5}', "temperature must be a finite number, got nan"),
        (
            '{"score": "ecr", "temperature": Infinity, "min_peak_z": 2.5}',
            "temperature must be a finite number, got inf",
        ),
        ('{"score": "ecr", "temperature": 0, "min_peak_z": 2.5}', r"temperature must be a finite number > 0, got 0"),
        ('{"score": "ecr", "temperature": -3, "min_peak_z": 2.5}', r"temperature must be a finite number > 0, got -3"),
        ('{"score": "ecr", "temperature": 2, "min_peak_z": NaN}', "min_peak_z must be a finite number, got nan"),
        (
            '{"score": "ecr", "temperature": true, "min_peak_z": 1}',
            "temperature must be a finite number, got a boolean",
        ),
        ('{"score": "nope", "temperature": 2, "min_peak_z": 1}', "score must be one of"),
    ],
)
def test_a_bad_calibration_file_is_refused_naming_the_file_and_the_key(tmp_path, text, match):
    path = tmp_path / "calibration.json"
    path.write_text(text)
    with pytest.raises(ValueError, match=match) as raised:
        Calibration.load(path)
    assert "calibration file" in str(raised.value) and str(path) in str(raised.value)


def test_a_binary_calibration_file_is_refused_naming_the_file(tmp_path):
    path = tmp_path / "calibration.json"
    path.write_bytes(b"\x80\x81\xff\x00")
    with pytest.raises(ValueError, match=r"calibration file .* is not readable JSON: it is not UTF-8 text"):
        Calibration.load(path)


@pytest.mark.parametrize(("temperature", "min_peak_z"), [(math.nan, 1.0), (0.0, 1.0), (-1.0, 1.0), (2.0, math.inf)])
def test_a_calibration_that_could_not_load_is_not_saved(tmp_path, temperature, min_peak_z):
    with pytest.raises(ValueError, match="must be a finite number"):
        Calibration("ecr", temperature, min_peak_z).save(tmp_path / "calibration.json")
    assert not (tmp_path / "calibration.json").exists()


def _bad_call(case: str):
    belief = initial_belief(torch.zeros(1, 3), shifts=2, yaw_bins=1)
    frame, reference = torch.rand(1, 1, 8, 8), torch.rand(1, 1, 32, 32)
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
        "captured batch": lambda: track_step(belief, torch.rand(2, 1, 8, 8), reference, odometry, 1.0),
        "reference shape": lambda: track_step(belief, frame, torch.rand(32, 32), odometry, 1.0),
        "score": lambda: track_step(belief, frame, reference, odometry, 1.0, score="ssd"),
        "temperature": lambda: TrackerSettings(temperature=0.0),
        "temperature name": lambda: TrackerSettings(temperature="grid"),
        "patience": lambda: TrackerSettings(patience=0),
        "coasting": lambda: TrackerSettings(coasting="constant"),
        "weak update": lambda: TrackerSettings(weak_update="use"),
        "motion noise": lambda: TrackerSettings(motion_noise=(0.1, 0.1)),
        "settings type": lambda: track_step(belief, frame, reference, odometry, 1.0, settings={"patience": 1}),
        "calibration and settings": lambda: Tracker(
            reference, settings=TrackerSettings(temperature=2.0), calibration=Calibration("ecr", 2.0, 3.0)
        ),
        "truth shape": lambda: calibrate_temperature(torch.zeros(4, 1, 3, 3), torch.zeros(4, 2)),
        "unknown setting": lambda: Tracker(reference, shift=3),
        "no start": lambda: Tracker(reference)(frame, odometry, 1.0),
        "variance twice": lambda: _started(Tracker(reference, ConstantVariance(1.0)))(frame, odometry, 1.0),
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
        ("captured batch", ValueError, r"captured must be \(B, 1, h, w\) with B = 1"),
        ("reference shape", ValueError, r"reference must be one map \(1, 1, Hm, Wm\)"),
        ("score", ValueError, "score must be a Score or one of"),
        ("temperature", ValueError, "temperature must be a finite number > 0"),
        ("temperature name", ValueError, "temperature must be 'auto' or a finite number > 0, got 'grid'"),
        ("patience", ValueError, "patience must be an int >= 1"),
        ("coasting", ValueError, r"coasting must be one of \['linear', 'random_walk'\], got 'constant'"),
        ("weak update", ValueError, r"weak_update must be one of \['nudge', 'skip'\], got 'use'"),
        ("motion noise", ValueError, "motion_noise must be three standard deviations >= 0"),
        ("truth shape", ValueError, r"truth \(N, 3\)"),
        ("settings type", TypeError, "settings must be a TrackerSettings or None, got dict"),
        ("calibration and settings", ValueError, "calibration sets temperature, min_peak_z, got settings with"),
        ("unknown setting", TypeError, "unexpected keyword argument 'shift'"),
        ("no start", RuntimeError, "call start"),
        ("variance twice", ValueError, "variance must be None when Tracker has a variance_model"),
    ],
)
def test_bad_inputs_raise_naming_the_argument(case, error, match):
    with pytest.raises(error, match=match):
        _bad_call(case)()


def _started(tracker: Tracker) -> Tracker:
    tracker.start(torch.tensor([[16.0, 16.0, 0.0]]))
    return tracker


@pytest.mark.parametrize("name", ["ecr", "nmi"])
def test_a_tracker_takes_the_score_by_name_or_object_alike(generator, name):
    reference = _texture(generator, (80, 120)).float()
    frame, odometry = _cut(reference, 62, 41), torch.tensor([[2.0, 1.0, 0.0]])
    variance = 1.0 if name == "ecr" else None
    outputs = []
    for score in (name, as_score(name)):
        tracker = Tracker(reference, settings=TrackerSettings(temperature=0.05), score=score, shifts=3, yaw_bins=3)
        tracker.start(torch.tensor([[60.0, 40.0, 0.0]]), std=(1.0, 1.0, 1.0))
        outputs.append(tracker(frame, odometry, variance))
    for first, second in zip(*outputs, strict=True):  # NaN alike: no refined pose without refine=True
        torch.testing.assert_close(first, second, rtol=0, atol=0, equal_nan=True)
    calibrated = Tracker(reference, calibration=Calibration(name, 0.05, 3.0), shifts=3, yaw_bins=3)
    calibrated.start(torch.tensor([[60.0, 40.0, 0.0]]), std=(1.0, 1.0, 1.0))
    assert torch.equal(calibrated(frame, odometry, variance).pose, outputs[0].pose)


def test_the_default_score_is_ecr_with_a_correlated_misfit_and_weighs_a_changed_patch_less(generator):
    from enmi_torch import ECR
    from enmi_torch.tracking import default_score

    assert default_score() == ECR(response="binned", misfit="correlated")
    reference = _texture(generator, (80, 120)).float()
    frame = _cut(reference, 62, 41).clone()
    frame[..., :12, :16] = 255 - frame[..., :12, :16]  # a changed patch of the scene
    frame = frame + 4 * torch.randn(frame.shape, generator=generator)
    odometry = torch.tensor([[2.0, 1.0, 0.0]])
    outputs = {}
    binned = ECR(response="binned")
    for name, score in (
        ("default", None),
        ("correlated", binned.replace(misfit="correlated")),
        ("independent", binned),
    ):
        tracker = Tracker(reference, score=score, shifts=3, yaw_bins=3)
        tracker.start(torch.tensor([[60.0, 40.0, 0.0]]), std=(1.0, 1.0, 1.0))
        outputs[name] = tracker(frame, odometry, 16.0)
    for first, second in zip(outputs["default"], outputs["correlated"], strict=True):
        torch.testing.assert_close(first, second, rtol=0, atol=0, equal_nan=True)
    # Both find the place; the changed patch is one piece of evidence, not 192 independent pixels.
    assert outputs["default"].pose[0, :2].round().tolist() == [62.0, 41.0]
    assert outputs["independent"].pose[0, :2].round().tolist() == [62.0, 41.0]
    assert float(outputs["default"].score[0]) < 0.5 * float(outputs["independent"].score[0])


def test_a_calibration_file_that_names_its_score_metric_still_loads(tmp_path):
    (tmp_path / "old.json").write_text('{"metric": "nmi", "temperature": 2.0, "min_peak_z": 3.5}')
    assert Calibration.load(tmp_path / "old.json") == Calibration("nmi", 2.0, 3.5)
    (tmp_path / "wrong.json").write_text('{"score": "mi", "temperature": 2.0, "min_peak_z": 3.5}')
    with pytest.raises(ValueError, match="score must be one of"):
        Calibration.load(tmp_path / "wrong.json")


def test_a_restart_moves_the_window_to_the_pose_on_the_yaw_lattice():
    from enmi_torch.tracking.step import _peak_position, _restart

    belief = initial_belief(torch.tensor([[10.0, 20.0, 20.0], [30.0, 40.0, -5.0]]), shifts=(2, 3), yaw_step=5.0)
    moved = _restart(belief, 0, torch.tensor([57.4, 31.6, 1.7], dtype=torch.float64))
    assert moved.center[0].tolist() == [32, 57] and moved.center[1].tolist() == [40, 30]  # (row, col); vehicle 1 kept
    assert moved.yaw_center.tolist() == [0.0, -5.0]  # 20 - 4 steps of 5: the lattice bin nearest 1.7
    likelihood = torch.zeros(2, 5, 5, 7, dtype=torch.float64)
    likelihood[1, 3, 4, 1] = 1.0  # yaw bin 3, row 4 of 5, column 1 of 7 (a non-square window)
    assert _peak_position(belief, likelihood, 1).tolist() == [30 + 1 - 3, 40 + 4 - 2]


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


def test_the_peak_z_score_of_a_nearly_flat_log_likelihood_stays_small():
    from enmi_torch.tracking.health import peak_z_score

    # A featureless frame: a few nats of bump on a log-likelihood whose MAD is a hundredth of a nat. Its z-score was
    # ~3e8, which passed every peak rule and, averaged into the recent matches' z, made every later match look weak.
    generator = torch.Generator().manual_seed(0)
    flat = 0.01 * torch.randn(5, 17, 17, generator=generator, dtype=torch.float64)
    flat[2, 8, 8] = 2.5
    median = flat.median()
    assert float(peak_z_score(flat)) > 100
    torch.testing.assert_close(peak_z_score(flat, min_spread=1.0), 2.5 - median)
    # A clear peak on a spread surface is not changed by the floor.
    spread = 30.0 * torch.randn(5, 17, 17, generator=generator, dtype=torch.float64)
    spread[2, 8, 8] = 400.0
    torch.testing.assert_close(peak_z_score(spread, min_spread=1.0), peak_z_score(spread))
    assert 8 < float(peak_z_score(spread)) < 20


def test_one_freak_peak_counts_at_most_twice_the_running_mean_of_the_matches():
    from enmi_torch.tracking.health import check_health, next_health

    health = check_health(None, 2, torch.device("cpu"))
    yes, no = torch.tensor([True, True]), torch.tensor([False, False])
    no_candidate = torch.full((2, 3), math.nan, dtype=torch.float64)
    health = next_health(
        health, yes, no, torch.zeros(2), torch.tensor([5.0, 5.0]), torch.tensor([8.0, 8.0]), no_candidate
    )
    health = next_health(
        health, yes, no, torch.zeros(2), torch.tensor([91.0, 6.0]), torch.tensor([8.0, 8.0]), no_candidate
    )
    torch.testing.assert_close(health.typical_z, torch.tensor([0.7 * 5 + 0.3 * 10, 0.7 * 5 + 0.3 * 6]).double())
    relocalized = next_health(health, yes, yes, torch.zeros(2), torch.tensor([91.0, 2.0]), torch.ones(2), no_candidate)
    assert relocalized.typical_z.tolist() == [91.0, 2.0]  # a relocalization starts afresh


def test_the_map_is_not_saved_with_the_tracker_state(generator):
    reference = _texture(generator, (40, 60)).float()
    tracker = Tracker(reference, score=ECR(bins=16), shifts=3, yaw_bins=1)
    assert torch.equal(tracker.reference, reference[None, None] if reference.ndim == 2 else reference)
    assert "reference" not in tracker.state_dict()  # a non-persistent buffer: checkpoints stay small


def test_clearness_is_one_for_a_usable_peak_the_squared_ratio_below_and_zero_where_ruled_out():
    from enmi_torch.tracking.health import Health, check_health, clearness

    fresh = check_health(None, 5, torch.device("cpu"))
    peak_z = torch.tensor([4.0, 1.5, 1.5, math.nan, 6.0], dtype=torch.float64)
    surprise = torch.tensor([0.0, 0.0, 40.0, 0.0, 0.0], dtype=torch.float64)
    weight = clearness(peak_z, surprise, fresh, min_peak_z=3.0, z_drop=0.3, max_surprise=30.0)
    # usable; (1.5 / 3)^2; ruled out by the prediction; no candidate; usable
    torch.testing.assert_close(weight, torch.tensor([1.0, 0.25, 0.0, 0.0, 1.0], dtype=torch.float64))
    # After matches of z 40, z_drop * 40 = 12 is the bar: a peak of 6 weighs (6 / 12)^2.
    seasoned = Health(
        fresh.weak_frames, torch.full((5,), 40.0, dtype=torch.float64), fresh.typical_temperature, fresh.candidate
    )
    weight = clearness(peak_z, surprise, seasoned, min_peak_z=3.0, z_drop=0.3, max_surprise=30.0)
    torch.testing.assert_close(
        weight, torch.tensor([(4 / 12) ** 2, (1.5 / 12) ** 2, 0.0, 0.0, 0.25], dtype=torch.float64)
    )


def test_a_weak_frame_nudges_the_belief_by_its_clearness_squared_or_is_skipped(generator):
    # One step from the same belief, three ways: a peak of z below min_peak_z = 2 z weighs (1 / 2)^2 = 1/4, so the
    # nudged log belief moves by a quarter of what the used frame's does; "skip" leaves the prediction.
    reference = _texture(generator, (80, 120)).float()
    belief = initial_belief(torch.tensor([[60.0, 40.0, 0.0]]), shifts=(4, 5), yaw_bins=1, std=(2.0, 1.5, 1.0))
    frame, odometry = _cut(reference, 61, 39), torch.zeros(1, 3)
    settings, score = TrackerSettings(motion_noise=(0.3, 0.3, 0.1)), ECR(bins=16)
    used, output, _ = track_step(belief, frame, reference, odometry, 1.0, score=score, settings=settings)
    assert bool(output.healthy[0])
    bar = 2 * float(output.peak_z[0])
    weak_settings = settings.replace(min_peak_z=bar)
    nudged, weak, _ = track_step(belief, frame, reference, odometry, 1.0, score=score, settings=weak_settings)
    skip_settings = weak_settings.replace(weak_update="skip")
    skipped, _, _ = track_step(belief, frame, reference, odometry, 1.0, score=score, settings=skip_settings)
    assert not bool(weak.healthy[0])
    prior = predict(belief, odometry, (0.3, 0.3, 0.1)).log_prob
    torch.testing.assert_close(skipped.log_prob, prior)
    moved, full = nudged.log_prob - prior, used.log_prob - prior
    torch.testing.assert_close(moved - moved.max(), 0.25 * (full - full.max()), rtol=1e-6, atol=1e-6)
    assert abs(float(weak.pose[0, 0]) - 60.0) > 0.05  # the nudge moves the pose towards the match at (61, 39)


def test_the_mismatch_mixing_takes_the_likelihood_at_a_fixed_temperature(generator):
    # The frame's raw log-likelihood (score * n_valid, from localize itself) divided by the temperature, then mixed.
    reference = _texture(generator, (60, 90)).float()
    belief = initial_belief(torch.tensor([[45.0, 30.0, 0.0]]), shifts=(4, 5), yaw_bins=3, std=(0.7, 0.7, 1.0))
    frame, odometry, noise = _cut(reference, 46, 31), torch.zeros(1, 3), (0.5, 0.5, 0.3)
    prior = predict(belief, odometry, noise)
    found = localize(
        frame, reference, 1.0, score=ECR(bins=16), shifts=prior.radius, center=prior.center, yaws=prior.yaws()[0]
    )
    raw = found.surface.double() * frame.numel()
    for temperature in (3000.0, 30000.0):  # a few nats and a fraction of one between the best cells
        settings = TrackerSettings(motion_noise=noise, temperature=temperature, mismatch_probability=0.05)
        posterior, output, _ = track_step(
            belief, frame, reference, odometry, 1.0, score=ECR(bins=16), settings=settings
        )
        assert bool(output.healthy[0])
        expected = normalized(prior.log_prob + mixed_with_mismatch(raw / temperature, 0.05))
        torch.testing.assert_close(posterior.log_prob, expected, atol=1e-6, rtol=0)


@pytest.mark.parametrize(
    ("offset", "previous", "yaw_step", "agree"),
    [
        ((10.0, -3.0, 1.0), (8.0, -5.0, -1.0), 1.0, True),  # 2 cells along x and y, 2 yaw bins: the edge agrees
        ((10.0, -3.0, 1.0), (7.9, -3.0, 1.0), 1.0, False),  # 2.1 cells along x
        ((10.0, -3.0, 1.0), (10.0, -0.9, 1.0), 1.0, False),  # 2.1 cells along y
        ((10.0, -3.0, 1.0), (10.0, -3.0, -1.1), 1.0, False),  # 2.1 yaw bins
        ((10.0, -3.0, 5.0), (10.0, -3.0, 1.0), 2.0, True),  # 4 degrees are 2 bins of 2 degrees
        ((10.0, -3.0, 5.0), (10.0, -3.0, 0.5), 2.0, False),  # 4.5 degrees are 2.25 bins
        ((10.0, -3.0, 1.0), (math.nan, math.nan, math.nan), 1.0, False),  # the previous frame found nothing
    ],
)
def test_two_wide_searches_agree_within_two_cells_and_two_yaw_bins(offset, previous, yaw_step, agree):
    from enmi_torch.tracking.step import wide_matches_agree

    offset, previous = torch.tensor(offset, dtype=torch.float64), torch.tensor(previous, dtype=torch.float64)
    assert wide_matches_agree(offset, previous, yaw_step) is agree
    assert wide_matches_agree(previous, offset, yaw_step) is (agree and bool(torch.isfinite(previous).all()))


def _frame_inputs(generator):
    reference = _texture(generator, (60, 90)).float()
    tracker = Tracker(reference, score=ECR(bins=16), shifts=3, yaw_bins=1)
    tracker.start(torch.tensor([[45.0, 30.0, 0.0]]))
    return tracker, _cut(reference, 45, 30), torch.zeros(1, 3)


@pytest.mark.parametrize(
    ("change", "error", "match"),
    [
        ({"captured_mask": torch.ones(1, 1, 8, 8, dtype=torch.bool)}, ValueError, "captured_mask must be as large as"),
        ({"captured_mask": torch.ones(1, 1, *FRAME)}, TypeError, "captured_mask must be a bool tensor"),
        ({"captured": "meta"}, ValueError, "captured must hold data, got a meta tensor"),
        ({"odometry": torch.zeros(3)}, ValueError, r"odometry must have shape \(1, 3\), rows \(x, y, yaw\)"),
        ({"odometry": torch.zeros(1, 2)}, ValueError, r"odometry must have shape \(1, 3\)"),
        ({"odometry": torch.zeros(1, 3, dtype=torch.long)}, TypeError, "odometry must be a floating-point tensor"),
        ({"variance": torch.ones(1, 1, 8, 8)}, ValueError, "variance must have the spatial shape of captured"),
    ],
)
def test_a_trackers_frame_inputs_are_refused_naming_the_argument(generator, change, error, match):
    tracker, frame, odometry = _frame_inputs(generator)
    arguments = {"captured": frame, "odometry": odometry, "variance": 1.0, "captured_mask": None}
    arguments.update(change)
    if arguments["captured"] == "meta":
        arguments["captured"] = frame.to("meta")
    with pytest.raises(error, match=match):
        tracker(**arguments)


def test_a_tracker_refuses_a_start_pose_of_the_wrong_shape_or_type(generator):
    tracker, _, _ = _frame_inputs(generator)
    for pose, error, match in (
        (torch.tensor([45.0, 30.0, 0.0]), ValueError, r"pose must have shape \(B, 3\), rows \(x, y, yaw\), got \(3,\)"),
        (torch.tensor([[45.0, 30.0]]), ValueError, r"pose must have shape \(B, 3\)"),
        (torch.tensor([[45, 30, 0]]), TypeError, "pose must be a floating-point tensor"),
        (torch.zeros(1, 3, device="meta"), ValueError, "pose must hold data, got a meta tensor"),
    ):
        with pytest.raises(error, match=match):
            tracker.start(pose)


def test_a_tracker_refuses_a_calibration_of_another_score():
    reference = torch.rand(1, 1, 32, 32) * 255
    with pytest.raises(ValueError, match=r"calibration was fitted for score 'ecr', got score='nmi'"):
        Tracker(reference, score="nmi", calibration=Calibration("ecr", 2.0, 3.0))
    tracker = Tracker(reference, score=ECR(bins=16), calibration=Calibration("ecr", 2.0, 3.0))
    assert tracker.settings.temperature == 2.0 and tracker.score == ECR(bins=16)


def test_a_tracker_refuses_a_belief_over_the_memory_budget_before_allocating():
    from enmi_torch import MemoryBudgetError

    reference = torch.rand(1, 1, 64, 64) * 255
    with pytest.raises(MemoryBudgetError, match=r"shifts=1000000 with yaw_bins=5 needs about .* TiB for the belief"):
        Tracker(reference, shifts=10**6)
    tracker = Tracker(reference, shifts=300, yaw_bins=1)  # one vehicle fits, a thousand do not
    with pytest.raises(MemoryBudgetError, match=r"for the belief \(1000, 1, 601, 601\)"):
        tracker.start(torch.zeros(1000, 3))
    for reference in (torch.rand(1, 1, 0, 4), torch.rand(2, 1, 8, 8), torch.rand(8, 8, device="meta")):
        with pytest.raises(ValueError, match=r"reference must (be one map|hold data)"):
            Tracker(reference)


def test_the_relocalization_gain_is_the_fresh_best_over_the_windows_best():
    from enmi_torch.tracking.step import relocalization_gain

    window = torch.tensor([[[[120.0, 150.0], [90.0, 10.0]]]], dtype=torch.float64)
    assert float(relocalization_gain(window + 7.5, window)) == 7.5
    assert float(relocalization_gain(window - 20.0, window)) == -20.0  # a worse match elsewhere: no jump
    assert float(relocalization_gain(torch.full_like(window, 155.0), window)) == 5.0


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
    from enmi_torch import memory_budget
    from enmi_torch.utils.budget import format_bytes

    expected = 8 * 8 * 4 * 3 * (2 * 300 + 1) * (2 * 200 + 1)  # 8 float64 copies of (4, 3, 601, 401)
    with memory_budget(1000), pytest.raises(MemoryBudgetError, match=rf"needs about {format_bytes(expected)} "):
        initial_belief(torch.zeros(4, 3), shifts=(300, 200), yaw_bins=3)


@pytest.mark.parametrize(
    ("peak_z", "temperature", "typical_z", "typical_temperature", "clear"),
    [
        (6.0, 30.0, 20.0, 100.0, True),  # z 6 >= 0.3 * 20, temperature 30 >= 0.3 * 100: the edges themselves pass
        (5.9, 30.0, 20.0, 100.0, False),  # a weaker peak than 0.3 of the recent matches'
        (6.0, 29.0, 20.0, 100.0, False),  # a flatter one
        (2.4, 30.0, 1.0, 1.0, False),  # below min_peak_z
        (2.5, 1.0, math.nan, math.nan, True),  # no recent match: only min_peak_z holds
    ],
)
def test_a_relocalization_peak_must_be_as_clear_and_sharp_as_the_recent_matches(
    peak_z, temperature, typical_z, typical_temperature, clear
):
    from enmi_torch.tracking.step import fresh_peak_is_clear

    values = (
        torch.tensor(value, dtype=torch.float64) for value in (peak_z, temperature, typical_z, typical_temperature)
    )
    assert fresh_peak_is_clear(*values, min_peak_z=2.5, z_drop=0.3) is clear
