"""The Tracker module: drives, coasting, relocalization, batching, scores, calibration, bad inputs."""

from __future__ import annotations

import math
import re

import pytest
import torch
from _tracking import FRAME, cut, texture

from enmi_torch import ECR, NCC, NMI, ConstantVariance
from enmi_torch.registration import warp_reference
from enmi_torch.scores import as_score
from enmi_torch.tracking import (
    Belief,
    Calibration,
    Tracker,
    TrackerSettings,
    belief_pose,
    initial_belief,
    predict,
    track_step,
)
from enmi_torch.tracking.belief import grid_poses, normalized
from enmi_torch.utils.budget import MemoryBudgetError


def _edge_drive(generator, steps: int, frame_of, start_x: float = 45.0) -> list:
    reference = texture(generator, (60, 90))
    settings = TrackerSettings(motion_noise=(0.3, 0.3, 0.1), patience=2, relocalize_shifts=6, coarse_factor=2)
    tracker = Tracker(reference.float(), settings=settings, score=ECR(bins=16), shifts=3, yaw_bins=1)
    tracker.start(torch.tensor([[start_x, 30.0, 0.0]]))
    return [frame_of(tracker, reference, step) for step in range(steps)]


def _position_variance(belief: Belief) -> torch.Tensor:
    """The ``(x, y)`` variance of a belief's bins, from their moments (no read-out rule in between)."""
    weights = normalized(belief.log_prob).exp()
    x, y, _ = grid_poses(belief)
    spread = []
    for values in (x.expand_as(weights), y.expand_as(weights)):
        mean = (weights * values).sum()
        spread.append((weights * (values - mean).square()).sum())
    return torch.stack(spread)


def _started(tracker: Tracker) -> Tracker:
    tracker.start(torch.tensor([[16.0, 16.0, 0.0]]))
    return tracker


def _frame_inputs(generator):
    reference = texture(generator, (60, 90)).float()
    tracker = Tracker(reference, score=ECR(bins=16), shifts=3, yaw_bins=1)
    tracker.start(torch.tensor([[45.0, 30.0, 0.0]]))
    return tracker, cut(reference, 45, 30), torch.zeros(1, 3)


@pytest.mark.parametrize(("temperature", "tolerance"), [(1.0, 1e-6), ("auto", 0.01)])
def test_noiseless_drive_is_tracked_exactly(generator, temperature, tolerance):
    # With the raw log-likelihood (temperature 1, the default before "auto") the pose is the cell itself; the default
    # flattens it to one bin's spread, which leaves the mean within a hundredth of a cell.
    reference = texture(generator, (96, 200))
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
        output = tracker(cut(reference, x, y).float(), torch.tensor([[float(du), float(dv), 0.0]]), 1.0)
        assert output.pose[0, :2].tolist() == pytest.approx([x, y], abs=tolerance)
        assert float(output.pose[0, 2]) == pytest.approx(0.0, abs=max(tolerance, 1e-3))  # nearest-neighbour turns
        assert bool(output.healthy[0]) and not bool(output.lost[0])


def test_a_fully_masked_frame_coasts_on_the_odometry(generator):
    def frame_of(tracker, reference, step):
        before = tracker.belief
        mask = torch.full((1, 1, *FRAME), step != 2)  # the third frame sees nothing
        output = tracker(cut(reference, 45 + 2 * (step + 1), 30).float(), torch.tensor([[2.0, 0.0, 0.0]]), 1.0, mask)
        return before, output

    outputs = _edge_drive(generator, 5, frame_of)
    before, masked = outputs[2]
    assert not bool(masked.healthy[0]) and math.isnan(float(masked.score[0])) and math.isnan(float(masked.peak_z[0]))
    coasted, _ = belief_pose(predict(before, torch.tensor([[2.0, 0.0, 0.0]]), (0.3, 0.3, 0.1)))
    torch.testing.assert_close(masked.pose, coasted)  # the prediction alone
    _, last = outputs[-1]
    assert bool(last.healthy[0]) and not bool(last.lost[0])
    assert last.pose[0, :2].tolist() == pytest.approx([55.0, 30.0], abs=0.05)


@pytest.mark.parametrize(
    ("coasting", "growth"), [(None, lambda k: k), ("linear", lambda k: k * k), ("random_walk", lambda k: k)]
)
def test_a_coasting_belief_widens_as_a_random_walk_by_default_or_as_a_bias(generator, coasting, growth):
    # Frames that see nothing: "random_walk" (the default) adds sigma^2 a frame; "linear" adds (2k + 1) sigma^2 after k
    # coasted frames, k^2 sigma^2 in all, a constant bias's spread. Unequal noise along u (x, the map's columns
    # at yaw 0) and v (y, rows) catches swapped axes.
    reference = texture(generator, (80, 120)).float()
    settings = TrackerSettings(motion_noise=(1.0, 0.6, 0.1))
    if coasting is not None:  # None: the default
        settings = settings.replace(coasting=coasting)
    tracker = Tracker(reference, settings=settings, score=ECR(bins=16), shifts=20, yaw_bins=1)
    tracker.start(torch.tensor([[60.0, 40.0, 0.0]]), std=(1.5, 1.5, 0.1))
    start_variance = _position_variance(tracker.belief)
    blind = torch.zeros(1, 1, *FRAME, dtype=torch.bool)
    for frames in range(1, 6):
        output = tracker(cut(reference, 60, 40).float(), torch.zeros(1, 3), 1.0, blind)
        added = _position_variance(tracker.belief) - start_variance
        expected = growth(frames) * torch.tensor([1.0, 0.36], dtype=torch.float64)
        torch.testing.assert_close(added, expected, rtol=0.04, atol=0.0)  # a discrete Gaussian, cut at 20 cells
        assert not bool(output.healthy[0]) and bool(output.lost[0]) == (frames >= 2)


def test_odometry_off_the_map_is_lost_then_found_again_without_an_exception(generator):
    # The odometry claims a jump of 200 cells (off the 90-cell map) for three frames, then returns: the windows there
    # hold no candidate (NoCandidateError inside, caught), the filter coasts and says lost, and recovers when back.
    def frame_of(tracker, reference, step):
        jump = {1: 200.0, 4: -200.0}.get(step, 0.0)
        return tracker(cut(reference, 45, 30).float(), torch.tensor([[jump, 0.0, 0.0]]), 1.0)

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
        output = tracker(cut(padded, x, 30).float(), torch.tensor([[2.0, 0.0, 0.0]]), 1.0, cut(valid, x, 30))
        return x, output

    outputs = _edge_drive(generator, 8, frame_of, start_x=74.0)
    for x, output in outputs:
        assert output.pose[0, :2].tolist() == pytest.approx([x, 30.0], abs=0.5)


def test_a_tracker_refines_each_used_frame_below_one_cell(generator):
    # Frames cut at sub-cell poses (bilinear): the belief stays on its cells, the refined pose finds the truth.
    reference = texture(generator, (96, 200))
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
    with pytest.raises(ValueError, match=r"register needs a score with the .least_squares. trait"):
        track_step(belief, frame, reference.float(), move.float(), settings=TrackerSettings(refine=True), score="nmi")


def test_a_kidnapped_vehicle_is_recovered_by_relocalization(generator):
    reference = texture(generator, (120, 240))
    settings = TrackerSettings(motion_noise=(0.3, 0.3, 0.1), patience=2, relocalize_shifts=40, coarse_factor=2)
    tracker = Tracker(reference.float(), settings=settings, score=ECR(bins=16), shifts=4, yaw_bins=1)
    tracker.start(torch.tensor([[40.0, 60.0, 0.0]]))
    x, y, recovered_after, relocalized = 40, 60, None, []
    for step in range(16):
        x += 3
        if step == 5:
            x, y = x + 25, y - 12  # the vehicle is carried away; odometry reports the usual move
        output = tracker(cut(reference, x, y).float(), torch.tensor([[3.0, 0.0, 0.0]]), 1.0)
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
    reference = texture(generator, (120, 240))
    settings = TrackerSettings(motion_noise=(0.3, 0.3, 0.1), patience=2, relocalize_shifts=40, coarse_factor=2)
    tracker = Tracker(reference.float(), settings=settings, score=ECR(bins=16), shifts=4, yaw_bins=1)
    tracker.start(torch.tensor([[40.0, 60.0, 0.0]]))
    x, y = 40, 60
    noise = torch.Generator().manual_seed(5)
    for step in range(12):
        x += 3
        frame = cut(reference, x, y)
        if step in (5, 6):
            frame = torch.rand(frame.shape, generator=noise, dtype=frame.dtype) * 256
        if step == 7:
            frame = cut(reference, x + 25, y - 12)
        output = tracker(frame.float(), torch.tensor([[3.0, 0.0, 0.0]]), 1.0)
        assert not bool(output.relocalized[0]), step
    assert float((output.pose[0, :2] - torch.tensor([x, y], dtype=torch.float64)).abs().max()) < 0.5
    assert bool(output.healthy[0]) and not bool(output.lost[0])


def test_a_weak_frame_whose_wide_search_lands_on_the_window_peak_is_used_without_a_jump(generator):
    # After clear frames (peak z ~60), noisy ones (z ~10) fall under z_drop times the recent matches' z: skipped. The
    # second such frame searches wide; its best match is the window's own peak, so the frame is used, no restart.
    reference = texture(generator, (120, 240))
    settings = TrackerSettings(motion_noise=(0.3, 0.3, 0.1), patience=2, relocalize_shifts=40, coarse_factor=2)
    tracker = Tracker(reference.float(), settings=settings, score=ECR(bins=16), shifts=4, yaw_bins=1)
    tracker.start(torch.tensor([[40.0, 60.0, 0.0]]))
    x, noise, outputs = 40, torch.Generator().manual_seed(1), []
    for step in range(7):
        x += 3
        frame, variance = cut(reference, x, 60), 1.0
        if step >= 5:
            frame, variance = frame + 100.0 * torch.randn(frame.shape, generator=noise, dtype=frame.dtype), 1e4
        outputs.append(tracker(frame.float(), torch.tensor([[3.0, 0.0, 0.0]]), variance))
    assert not bool(outputs[5].healthy[0]) and 3.0 <= float(outputs[5].peak_z[0]) < 0.3 * float(outputs[4].peak_z[0])
    assert bool(outputs[6].healthy[0]) and not bool(outputs[6].relocalized[0])
    assert float((outputs[6].pose[0, :2] - torch.tensor([x, 60.0], dtype=torch.float64)).abs().max()) < 0.1


def test_batched_vehicles_equal_one_at_a_time(generator):
    reference = texture(generator, (80, 120)).float()
    starts = torch.tensor([[40.0, 30.0, 0.0], [70.0, 45.0, 0.0]])
    odometry = torch.tensor([[2.0, 1.0, 0.0], [-1.0, 2.0, 0.0]])
    frames = torch.cat([cut(reference, 42, 31), cut(reference, 69, 47)])
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
    reference = texture(generator, (80, 120)).float()
    tracker = Tracker(reference, settings=TrackerSettings(temperature=0.01), score=NMI(bins=16), shifts=3, yaw_bins=3)
    tracker.start(torch.tensor([[60.0, 40.0, 0.0]]), std=(1.0, 1.0, 1.0))
    start = tracker.belief
    frame, odometry = cut(reference, 62, 41), torch.tensor([[2.0, 1.0, 0.0]])
    output = tracker(frame, odometry)
    settings = TrackerSettings(temperature=0.01)
    belief, expected, health = track_step(
        start, frame, reference, odometry, None, score=NMI(bins=16), settings=settings
    )
    torch.testing.assert_close(output.pose, expected.pose)
    torch.testing.assert_close(tracker.belief.log_prob, belief.log_prob)
    assert health.weak_frames.tolist() == tracker.health.weak_frames.tolist()


@pytest.mark.parametrize("name", ["ecr", "nmi"])
def test_a_tracker_takes_the_score_by_name_or_object_alike(generator, name):
    reference = texture(generator, (80, 120)).float()
    frame, odometry = cut(reference, 62, 41), torch.tensor([[2.0, 1.0, 0.0]])
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


def test_the_map_is_not_saved_with_the_tracker_state(generator):
    reference = texture(generator, (40, 60)).float()
    tracker = Tracker(reference, score=ECR(bins=16), shifts=3, yaw_bins=1)
    assert torch.equal(tracker.reference, reference[None, None] if reference.ndim == 2 else reference)
    assert "reference" not in tracker.state_dict()  # a non-persistent buffer: checkpoints stay small


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


@pytest.mark.parametrize(
    ("recorded", "given", "expected"),
    [
        (None, None, "per_frame"),  # written before the noise model was recorded: fitted per frame, used so
        ("per_frame", None, "per_frame"),
        ("held", None, "held"),
        ("per_frame", "per_frame", "per_frame"),
        ("held", "per_frame", "held"),  # "per_frame" is the default: not told apart from no setting, like temperature's
        ("per_frame", "held", None),
        (None, "held", None),
    ],
)
def test_a_calibration_sets_the_noise_model_it_was_fitted_with(recorded, given, expected):
    reference = torch.rand(1, 1, 32, 32) * 255
    settings = TrackerSettings() if given is None else TrackerSettings(noise_model=given)
    calibration = Calibration("ecr", 2.0, 3.0, recorded)
    if expected is None:
        with pytest.raises(
            ValueError,
            match=r"calibration was fitted with noise_model='per_frame', got settings with "
            r"noise_model='held': leave noise_model out",
        ):
            Tracker(reference, settings=settings, calibration=calibration)
        return
    tracker = Tracker(reference, settings=settings, calibration=calibration)
    assert tracker.settings.noise_model == expected and tracker.score == ECR()


def test_a_tracker_refuses_a_belief_over_the_memory_budget_before_allocating():

    reference = torch.rand(1, 1, 64, 64) * 255
    with pytest.raises(MemoryBudgetError, match=r"shifts=1000000 with yaw_bins=5 needs about .* TiB for the belief"):
        Tracker(reference, shifts=10**6)
    tracker = Tracker(reference, shifts=300, yaw_bins=1)  # one vehicle fits, a thousand do not
    with pytest.raises(MemoryBudgetError, match=r"for the belief \(1000, 1, 601, 601\)"):
        tracker.start(torch.zeros(1000, 3))
    for reference in (torch.rand(1, 1, 0, 4), torch.rand(2, 1, 8, 8), torch.rand(8, 8, device="meta")):
        with pytest.raises(ValueError, match=r"reference must (be one map|hold data)"):
            Tracker(reference)


def _bad_call(case: str):
    frame, reference = torch.rand(1, 1, 8, 8), torch.rand(1, 1, 32, 32)
    odometry = torch.zeros(1, 3)
    calls = {
        "calibration and settings": lambda: Tracker(
            reference, settings=TrackerSettings(temperature=2.0), calibration=Calibration("ecr", 2.0, 3.0)
        ),
        "unknown setting": lambda: Tracker(reference, shift=3),
        "no start": lambda: Tracker(reference)(frame, odometry, 1.0),
        "variance twice": lambda: _started(Tracker(reference, ConstantVariance(1.0)))(frame, odometry, 1.0),
    }
    return calls[case]


@pytest.mark.parametrize(
    ("case", "error", "match"),
    [
        ("calibration and settings", ValueError, "calibration sets temperature, min_peak_z, got settings with"),
        ("unknown setting", TypeError, "unexpected keyword argument 'shift'"),
        ("no start", RuntimeError, "call start"),
        ("variance twice", ValueError, "variance must be None when Tracker has a variance_model"),
    ],
)
def test_bad_inputs_raise_naming_the_argument(case, error, match):
    with pytest.raises(error, match=match):
        _bad_call(case)()


def test_a_relocalization_reads_the_noise_model_at_its_own_peak(generator):
    # The vehicle is carried 25 cells right and 12 up onto a patch seen through a larger misfit (noise beyond the
    # variance given): the relocalized frame's tau^2 is ECR's own on the pair at the place it restarts from.
    reference = texture(generator, (120, 240))
    settings = TrackerSettings(
        motion_noise=(0.3, 0.3, 0.1), patience=2, relocalize_shifts=40, coarse_factor=2, noise_model="held"
    )
    score = ECR(bins=16)
    tracker = Tracker(reference.float(), settings=settings, score=score, shifts=4, yaw_bins=1)
    tracker.start(torch.tensor([[40.0, 60.0, 0.0]]))
    x, y, relocalized = 40, 60, []
    for step in range(12):
        x += 3
        if step == 5:
            x, y = x + 25, y - 12
        sigma = 1.0 if step < 5 else 4.0
        frame = cut(reference, x, y) + sigma * torch.randn(1, 1, *FRAME, generator=generator, dtype=torch.float64)
        output = tracker(frame.float(), torch.tensor([[3.0, 0.0, 0.0]]), 1.0)
        if bool(output.relocalized[0]):
            relocalized.append(step)
            held = tracker.health.held[0]
            height, width = FRAME
            section = reference[
                ..., y - height // 2 : y - height // 2 + height, x - width // 2 : x - width // 2 + width
            ]
            pair = (frame.float().double(), section.float().double(), 1.0)
            expected = (float(score.model_variance_of(*pair)[0]), float(score.response_variance_of(*pair)[0]))
            assert held is not None and (held.model_variance, held.response_variance) == pytest.approx(expected)
    assert len(relocalized) == 1 and tracker.health.held[0] is held
    assert float((output.pose[0, :2] - torch.tensor([x, y], dtype=torch.float64)).abs().max()) < 0.5


@pytest.mark.parametrize(
    "score",
    [NMI(), NCC(), ECR(model_variance=100.0, response_variance=50.0), ECR(response="binned", model_variance=100.0)],
    ids=repr,
)
def test_a_held_noise_model_is_refused_naming_a_score_that_estimates_none(generator, score):
    reference = texture(generator, (60, 90)).float()
    settings = TrackerSettings(noise_model="held")
    message = rf"^noise_model='held' has no effect with score={re.escape(repr(score))}: it estimates no noise model"
    with pytest.raises(ValueError, match=message):
        Tracker(reference, score=score, settings=settings)
    belief = initial_belief(torch.tensor([[45.0, 30.0, 0.0]]), shifts=2, yaw_bins=1)
    frame = cut(reference, 45, 30).float() + 1.0
    variance = 1.0 if score.uses_variance else None
    with pytest.raises(ValueError, match=message):
        track_step(belief, frame, reference, torch.zeros(1, 3), variance, score=score, settings=settings)
    assert Tracker(reference, score=score).settings.noise_model == "per_frame"  # the default: nothing to refuse
    # A score that estimates tau^2 or delta^2 holds it.
    for held in (ECR(model_variance=100.0), ECR(response="binned"), ECR()):
        assert Tracker(reference, score=held, settings=settings).settings.noise_model == "held"
