"""One filter step: mismatch mixing, weak frames, wide searches and relocalization rules, bad inputs."""

from __future__ import annotations

import math

import pytest
import torch
from _tracking import FRAME, cut, texture

from enmi_torch import ECR, localize
from enmi_torch.localization import NoCandidateError
from enmi_torch.tracking import Tracker, TrackerSettings, initial_belief, predict, track_step
from enmi_torch.tracking.belief import mixed_with_mismatch, normalized


def test_a_mismatch_probability_bounds_how_far_one_wrong_frame_moves_the_belief(generator):
    # The belief is sure of (45, 30); the frame is the map 3 cells right and 2 down, a sharp, clear wrong match.
    reference = texture(generator, (60, 90)).float()
    belief = initial_belief(torch.tensor([[45.0, 30.0, 0.0]]), shifts=(4, 5), yaw_bins=1, std=(0.7, 0.7, 1.0))
    frame, odometry, noise = cut(reference, 48, 32), torch.zeros(1, 3), (0.5, 0.5, 0.3)
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


def test_a_window_without_candidates_raises_no_candidate_error(generator):
    reference = texture(generator, (40, 60)).float()
    with pytest.raises(NoCandidateError, match="the search window lies off the map"):
        localize(cut(reference, 30, 20), reference, 1.0, shifts=3, around=(500, 20))


def test_the_default_score_is_ecr_with_a_correlated_misfit_and_weighs_a_changed_patch_less(generator):
    from enmi_torch import ECR
    from enmi_torch.tracking import default_score

    assert default_score() == ECR(response="binned", misfit="correlated")
    reference = texture(generator, (80, 120)).float()
    frame = cut(reference, 62, 41).clone()
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


def test_a_restart_moves_the_window_to_the_pose_on_the_yaw_lattice():
    from enmi_torch.tracking.step import _peak_position, _restart

    belief = initial_belief(torch.tensor([[10.0, 20.0, 20.0], [30.0, 40.0, -5.0]]), shifts=(2, 3), yaw_step=5.0)
    moved = _restart(belief, 0, torch.tensor([57.4, 31.6, 1.7], dtype=torch.float64))
    assert moved.center[0].tolist() == [32, 57] and moved.center[1].tolist() == [40, 30]  # (row, col); vehicle 1 kept
    assert moved.yaw_center.tolist() == [0.0, -5.0]  # 20 - 4 steps of 5: the lattice bin nearest 1.7
    likelihood = torch.zeros(2, 5, 5, 7, dtype=torch.float64)
    likelihood[1, 3, 4, 1] = 1.0  # yaw bin 3, row 4 of 5, column 1 of 7 (a non-square window)
    assert _peak_position(belief, likelihood, 1).tolist() == [30 + 1 - 3, 40 + 4 - 2]


def test_a_weak_frame_nudges_the_belief_by_its_clearness_squared_or_is_skipped(generator):
    # One step from the same belief, three ways: a peak of z below min_peak_z = 2 z weighs (1 / 2)^2 = 1/4, so the
    # nudged log belief moves by a quarter of what the used frame's does; "skip" leaves the prediction.
    reference = texture(generator, (80, 120)).float()
    belief = initial_belief(torch.tensor([[60.0, 40.0, 0.0]]), shifts=(4, 5), yaw_bins=1, std=(2.0, 1.5, 1.0))
    frame, odometry = cut(reference, 61, 39), torch.zeros(1, 3)
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
    reference = texture(generator, (60, 90)).float()
    belief = initial_belief(torch.tensor([[45.0, 30.0, 0.0]]), shifts=(4, 5), yaw_bins=3, std=(0.7, 0.7, 1.0))
    frame, odometry, noise = cut(reference, 46, 31), torch.zeros(1, 3), (0.5, 0.5, 0.3)
    prior = predict(belief, odometry, noise)
    around = prior.center.flip(1)  # the window's (row, col) as (x, y)
    options = {"score": ECR(bins=16), "shifts": prior.radius, "around": around, "yaws": prior.yaws()[0]}
    found = localize(frame, reference, 1.0, **options)
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


def test_the_relocalization_gain_is_the_fresh_best_over_the_windows_best():
    from enmi_torch.tracking.step import relocalization_gain

    window = torch.tensor([[[[120.0, 150.0], [90.0, 10.0]]]], dtype=torch.float64)
    assert float(relocalization_gain(window + 7.5, window)) == 7.5
    assert float(relocalization_gain(window - 20.0, window)) == -20.0  # a worse match elsewhere: no jump
    assert float(relocalization_gain(torch.full_like(window, 155.0), window)) == 5.0


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


def _bad_call(case: str):
    belief = initial_belief(torch.zeros(1, 3), shifts=2, yaw_bins=1)
    frame, reference = torch.rand(1, 1, 8, 8), torch.rand(1, 1, 32, 32)
    odometry = torch.zeros(1, 3)
    calls = {
        "captured batch": lambda: track_step(belief, torch.rand(2, 1, 8, 8), reference, odometry, 1.0),
        "reference shape": lambda: track_step(belief, frame, torch.rand(32, 32), odometry, 1.0),
        "score": lambda: track_step(belief, frame, reference, odometry, 1.0, score="ssd"),
        "settings type": lambda: track_step(belief, frame, reference, odometry, 1.0, settings={"patience": 1}),
    }
    return calls[case]


@pytest.mark.parametrize(
    ("case", "error", "match"),
    [
        ("captured batch", ValueError, r"captured must be \(B, 1, h, w\) with B = 1"),
        ("reference shape", ValueError, r"reference must be one map \(1, 1, Hm, Wm\)"),
        ("score", ValueError, "score must be a Score or one of"),
        ("settings type", TypeError, "settings must be a TrackerSettings or None, got dict"),
    ],
)
def test_bad_inputs_raise_naming_the_argument(case, error, match):
    with pytest.raises(error, match=match):
        _bad_call(case)()


def _aligned_estimate(frame, reference, x, y, variance, score):
    """ECR's own ``tau^2`` and ``delta^2`` on the frame and the map section under cell ``(x, y)`` (yaw 0), float64."""
    height, width = frame.shape[2:]
    section = reference[..., y - height // 2 : y - height // 2 + height, x - width // 2 : x - width // 2 + width]
    pair = (frame.double(), section.double(), variance)
    return float(score.model_variance_of(*pair)[0]), float(score.response_variance_of(*pair)[0])


def test_the_noise_model_is_read_at_the_first_used_frame_and_held_across_the_next(generator):
    # Frames of changing noise (a per-frame estimate would change with them): the first used frame's tau^2 and
    # delta^2 are ECR's own on its pair, and every later frame is scored with them, not its own.
    reference = texture(generator, (80, 140)).float()
    score, settings = ECR(bins=16), TrackerSettings(motion_noise=(0.5, 0.5, 0.3), noise_model="held")
    tracker = Tracker(reference, score=score, settings=settings, shifts=(3, 4), yaw_bins=1)
    tracker.start(torch.tensor([[40.0, 40.0, 0.0]]))
    assert tracker.settings.noise_model == "held"
    x, first = 40, None
    for step, sigma in enumerate((3.0, 12.0, 1.0, 20.0)):
        x += 3
        frame = (cut(reference, x, 40) + sigma * torch.randn(1, 1, *FRAME, generator=generator)).float()
        belief, health = tracker.belief, tracker.health
        output = tracker(frame, torch.tensor([[3.0, 0.0, 0.0]]), sigma**2)
        assert bool(output.healthy[0])
        held = tracker.health.held[0]
        if step == 0:
            first = held
            tau2, delta2 = _aligned_estimate(frame, reference, x, 40, sigma**2, score)
            assert (held.model_variance, held.response_variance) == pytest.approx((tau2, delta2), rel=1e-12)
            assert held == score.replace(model_variance=tau2, response_variance=delta2)
            continue
        assert held is first  # held, not re-read
        # The frame's likelihood is the held score's surface: the same step with the held score given outright.
        _, alone, _ = track_step(
            belief,
            frame,
            reference,
            torch.tensor([[3.0, 0.0, 0.0]]),
            sigma**2,
            score=first,
            settings=settings.replace(noise_model="per_frame"),
            health=health._replace(held=(None,)),
        )
        torch.testing.assert_close(output.score, alone.score, rtol=0, atol=0)
        torch.testing.assert_close(output.pose, alone.pose)
        own, _ = _aligned_estimate(frame, reference, x, 40, sigma**2, score)
        assert abs(own - first.model_variance) > 1e-3 * first.model_variance  # a per-frame read would differ


def test_the_held_noise_model_is_dropped_when_lost_and_read_again_at_the_next_used_frame(generator):
    reference = texture(generator, (80, 140)).float()
    score, settings = ECR(bins=16), TrackerSettings(motion_noise=(0.3, 0.3, 0.1), patience=2, noise_model="held")
    tracker = Tracker(reference, score=score, settings=settings, shifts=3, yaw_bins=1)
    tracker.start(torch.tensor([[40.0, 40.0, 0.0]]))
    blind = torch.zeros(1, 1, *FRAME, dtype=torch.bool)
    held, x = [], 40
    for step in range(6):
        x += 2
        sigma = 2.0 if step < 3 else 12.0  # the noise beyond the variance given (1) is the model's misfit, tau^2
        frame = (cut(reference, x, 40) + sigma * torch.randn(blind.shape, generator=generator)).float()
        output = tracker(frame, torch.tensor([[2.0, 0.0, 0.0]]), 1.0, None if step not in (1, 2) else blind)
        held.append(tracker.health.held[0])
        if step == 3:
            tau2, delta2 = _aligned_estimate(frame, reference, x, 40, 1.0, score)
    assert [one is None for one in held] == [False, False, True, False, False, False]  # lost at the second blind one
    assert held[1] is held[0]  # one blind frame: not lost, still held
    assert bool(output.healthy[0]) and held[4] is held[3] and held[5] is held[3]
    assert (held[3].model_variance, held[3].response_variance) == pytest.approx((tau2, delta2), rel=1e-12)
    assert held[3].model_variance > 4 * held[0].model_variance  # read anew, at the frame of the larger misfit


def test_per_frame_noise_models_hold_nothing_and_score_each_frame_with_the_score_itself(generator):
    reference = texture(generator, (80, 120)).float()
    belief = initial_belief(torch.tensor([[60.0, 40.0, 0.0]]), shifts=3, yaw_bins=1)
    frame, odometry = cut(reference, 61, 41).float(), torch.tensor([[1.0, 1.0, 0.0]])
    settings = TrackerSettings(motion_noise=(0.5, 0.5, 0.3), noise_model="per_frame")
    _, output, health = track_step(belief, frame, reference, odometry, 4.0, score=ECR(bins=16), settings=settings)
    assert bool(output.healthy[0]) and health.held == (None,)
    prior = predict(belief, odometry, (0.5, 0.5, 0.3))
    found = localize(frame, reference, 4.0, score=ECR(bins=16), shifts=3, around=prior.center.flip(1), yaws=[0.0])
    assert float(output.score[0]) == pytest.approx(float(found.surface.max()), rel=1e-12)


def test_a_held_regional_misfit_is_refused_naming_the_setting_that_reads_it_per_frame(generator):
    reference = texture(generator, (60, 90)).float()
    belief = initial_belief(torch.tensor([[45.0, 30.0, 0.0]]), shifts=2, yaw_bins=1)
    frame = cut(reference, 45, 30).float() + 1.0
    score = ECR(bins=16, misfit="regional")
    with pytest.raises(ValueError, match=r"misfit='regional'.*TrackerSettings\(noise_model='per_frame'\)"):
        track_step(
            belief, frame, reference, torch.zeros(1, 3), 1.0, score=score, settings=TrackerSettings(noise_model="held")
        )
    _, output, _ = track_step(
        belief, frame, reference, torch.zeros(1, 3), 1.0, score=score, settings=TrackerSettings(noise_model="per_frame")
    )
    assert bool(output.healthy[0])
