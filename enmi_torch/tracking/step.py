"""One frame of the histogram (Bayes) filter, :func:`track_step`: predict, update by a score surface, read the pose.

* predict: the belief (:mod:`~enmi_torch.tracking.belief`) moves by the odometry and is blurred by its noise, over
  frames without a used match as a random walk (default) or as an odometry bias would (``coasting="linear"``,
  :func:`coasting_noise`);
* update: the score surface over the belief's window, turned into a log-likelihood ``score * n_valid /
  temperature`` (``n_valid`` the captured image's valid pixels; by default each frame's temperature is
  :func:`~enmi_torch.tracking.calibration.grid_temperature`, which needs no calibration, or one fitted on surveyed
  frames by :func:`~enmi_torch.tracking.calibrate_temperature`), is added to the log belief;
* read: pose and covariance are the posterior's moments;
* health (:mod:`~enmi_torch.tracking.health`): a frame whose surface has no clear peak only nudges the belief (its
  log-likelihood scaled by its :func:`~enmi_torch.tracking.health.clearness`), one whose peak the prediction rules
  out is not used; after ``patience`` such frames the filter searches a wider window (a coarse-to-fine
  :func:`~enmi_torch.localize`): if that search lands on the window's own peak the frame is used after all, and if it
  finds a match better than the window's by ``relocalize_odds`` nats where the previous frame's wide search found its
  own (two frames agreeing), the filter restarts there (relocalization);
* a window with no candidate at all (off the map, a frame fully masked: :class:`~enmi_torch.NoCandidateError` from
  the search) is a frame without a match: the belief coasts on the odometry. ``lost`` says that the filter has gone
  ``patience`` frames without a match and the wide search has not found the vehicle again.

The settings of all of these are one :class:`~enmi_torch.tracking.TrackerSettings`.

Convention:
    Poses and odometry as in :mod:`~enmi_torch.tracking.belief`; searches run without gradient.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from enmi_torch.registration.refine import check_registration_score
from enmi_torch.scores import ECR, Score, as_score
from enmi_torch.tracking.belief import (
    Belief,
    belief_pose,
    check_belief,
    check_noise,
    mixed_with_mismatch,
    normalized,
    predict,
)
from enmi_torch.tracking.health import Health, check_health, clearness, next_health, prediction_surprise
from enmi_torch.tracking.search import FrameSearch
from enmi_torch.tracking.settings import COASTING, TrackerSettings, refuse_moved_tracker_keywords
from enmi_torch.utils.checks import check_floating, check_mask_of, check_option, check_real_data, check_same_device
from enmi_torch.variance.base import VarianceModel


class TrackOutput(NamedTuple):
    """What one filter step reports per vehicle.

    Attributes:
        pose: ``(B, 3)`` posterior mean ``(x, y, yaw)``: map column and row in cells, yaw in degrees.
        covariance: ``(B, 3, 3)`` posterior covariance of ``(x, y, yaw)`` (cells², cells x degrees, degrees²).
        healthy: ``(B,)`` bool: this frame's match was used in full (a clear peak that the prediction allows); a weak
            frame only nudges the belief (``weak_update``).
        relocalized: ``(B,)`` bool: the filter searched the wide window this frame and restarted there.
        score: ``(B,)`` best score of the frame's surface (NaN where the window had no candidate).
        peak_z: ``(B,)`` the peak's robust z-score over the frame's log-likelihood ``score * n_valid``
            (``(best - median) / max(1.4826 MAD, 1 nat)``, :func:`~enmi_torch.tracking.health.peak_z_score`; NaN
            where the window had no candidate).
        lost: ``(B,)`` bool: ``patience`` or more frames in a row without a usable match, and no relocalization
            yet: the pose is dead reckoning and the belief grows with the odometry's noise.
        refined: ``(B, 3)`` this frame's own continuous pose, :func:`~enmi_torch.register` from ``pose`` (within one
            cell of it), where the frame's match was used and ``refine=True``; NaN elsewhere. The belief itself
            stays on its grid.
    """

    pose: Tensor
    covariance: Tensor
    healthy: Tensor
    relocalized: Tensor
    score: Tensor
    peak_z: Tensor
    lost: Tensor
    refined: Tensor


@refuse_moved_tracker_keywords
def track_step(
    belief: Belief,
    captured: Tensor,
    reference: Tensor,
    odometry: Tensor,
    variance: Tensor | float | VarianceModel | None = None,
    captured_mask: Tensor | None = None,
    *,
    score: Score | str | None = None,
    settings: TrackerSettings | None = None,
    health: Health | None = None,
) -> tuple[Belief, TrackOutput, Health]:
    """One frame of the filter: predict by ``odometry``, update by the frame's score surface, read the pose.

    Args:
        belief: the belief after the previous frame (:func:`~enmi_torch.tracking.initial_belief` for the first).
        captured: ``(B, 1, h, w)`` captured images on the map's cell grid, one per vehicle.
        reference: ``(1, 1, Hm, Wm)`` the map.
        odometry: ``(B, 3)`` increment since the previous frame (see :func:`~enmi_torch.tracking.predict`).
        variance: the captured images' noise variance for a score that uses one (ECR, ENMI, mixture): a number,
            ``(h, w)``, ``(1 or B, 1, h, w)`` or a :class:`~enmi_torch.variance.VarianceModel`; ``None`` for NMI and
            NCC.
        captured_mask: bool, like ``variance``: ``False`` pixels are unobserved.
        score: the score of the surfaces, a :class:`~enmi_torch.scores.Score` or its name (see
            :func:`~enmi_torch.localize`); ``None`` (default): :func:`default_score`, ECR with a spatially correlated
            misfit and the binned response.
        settings: the motion noise, likelihood scale, health rules and relocalization search
            (:class:`~enmi_torch.tracking.TrackerSettings`); ``None``: its defaults.
        health: the :class:`~enmi_torch.tracking.Health` from the previous step (``None`` at the start).

    Returns:
        ``(belief, output, health)``: the posterior :class:`~enmi_torch.tracking.Belief`, the :class:`TrackOutput`
        and the :class:`~enmi_torch.tracking.Health` for the next step.
    """
    check_belief(belief)
    settings = check_settings(settings)
    score = default_score() if score is None else as_score(score)
    check_noise_model(settings, score)
    if settings.refine:
        check_registration_score(score)
    check_floating("captured", captured)
    check_real_data("captured", captured)
    if captured.ndim != 4 or captured.shape[1] != 1 or captured.shape[0] != belief.log_prob.shape[0]:
        raise ValueError(
            f"captured must be (B, 1, h, w) with B = {belief.log_prob.shape[0]} (the belief's vehicles), got "
            f"{tuple(captured.shape)}"
        )
    check_reference_map(reference)
    check_same_device("captured", captured, "reference", reference)
    if captured_mask is not None:
        captured_mask = check_mask_of("captured_mask", captured_mask, "captured", captured)
    health = check_health(health, captured.shape[0], captured.device)
    search = FrameSearch(captured, reference, variance, captured_mask, score, health.held)
    prior = predict(belief, odometry, coasting_noise(settings.motion_noise, health.weak_frames, settings.coasting))
    raw, best_score, peak_z, frame_temperature = search.window(prior)
    temperature = settings.temperature
    if temperature == "auto":
        # A frame without a clear peak (a featureless stretch) is read at the scale of the recent clear matches.
        typical = health.typical_temperature
        temperature = torch.where(torch.isfinite(typical), torch.fmax(typical, frame_temperature), frame_temperature)
        temperature = torch.where(torch.isfinite(temperature), temperature, 1.0)[:, None, None, None]
    log_likelihood = raw / temperature
    surprise = prediction_surprise(prior.log_prob, log_likelihood)
    weight = clearness(peak_z, surprise, health, settings.min_peak_z, settings.z_drop, settings.max_surprise)
    healthy = weight >= 1
    weak_frames = torch.where(healthy, 0, health.weak_frames + 1)
    relocalized = torch.zeros_like(healthy)
    log_prob = prior.log_prob.clone()
    center, yaw_center = prior.center.clone(), prior.yaw_center.clone()
    candidate = torch.full_like(health.candidate, math.nan)
    held = list(health.held)
    for vehicle in (weak_frames >= settings.patience).nonzero()[:, 0].tolist():
        found = search.wide(
            vehicle, prior, settings.relocalize_shifts, settings.relocalize_yaw_bins, settings.coarse_factor
        )
        if found is None:
            continue  # nothing to match in the wide window either (off the map): keep coasting
        window_peak = _peak_position(prior, log_likelihood, vehicle)
        near = bool((window_peak - found[:2].to(window_peak)).abs().max() <= 1.5)
        if near and bool(peak_z[vehicle] >= settings.min_peak_z):
            healthy[vehicle] = True  # the wide search confirms the window's own peak: use the frame
            continue
        # One frame's best match over the wide window is the best of many noisy candidates: jump only where the
        # previous frame's wide search found the same place (relative to the predicted window, within 2 cells and
        # 2 yaw bins), so that a lone false peak in a noisy stretch does not move a filter that was right.
        window_center = torch.stack([center[vehicle, 1], center[vehicle, 0], yaw_center[vehicle]]).to(candidate)
        offset = found.to(candidate) - window_center
        previous = health.candidate[vehicle]
        candidate[vehicle] = offset
        if not wide_matches_agree(offset, previous, prior.yaw_step):
            continue
        fresh = _restart(prior, vehicle, found)
        fresh_raw, fresh_score, fresh_z, fresh_temperature = search.window(fresh, vehicle)
        fresh_likelihood = fresh_raw / (temperature[vehicle] if isinstance(temperature, Tensor) else temperature)
        gain = relocalization_gain(fresh_likelihood[0], log_likelihood[vehicle])
        typical = health.typical_z[vehicle], health.typical_temperature[vehicle]
        clear = fresh_peak_is_clear(fresh_z[0], fresh_temperature[0], *typical, settings.min_peak_z, settings.z_drop)
        if clear and bool(gain >= settings.relocalize_odds):
            log_prob[vehicle] = normalized(fresh_likelihood)[0]
            center[vehicle], yaw_center[vehicle] = fresh.center[vehicle], fresh.yaw_center[vehicle]
            best_score[vehicle], peak_z[vehicle], relocalized[vehicle] = fresh_score[0], fresh_z[0], True
            frame_temperature[vehicle] = fresh_temperature[0]  # the match the belief restarts from
            if settings.noise_model == "held":
                held[vehicle] = search.held_fit(vehicle, fresh, fresh_likelihood[0])
    # How much of the frame the belief takes: all of a used match (a wide search may have confirmed a weak peak),
    # its clearness of a weak one when nudging, none of a relocalized frame (its belief restarted from it).
    nudge = weight if settings.weak_update == "nudge" else 0.0
    share = torch.where(healthy, 1.0, nudge).masked_fill(relocalized, 0.0)
    taken = (share > 0)[:, None, None, None]
    share = share.to(log_likelihood)[:, None, None, None]
    if settings.mismatch_probability > 0:
        log_likelihood = mixed_with_mismatch(log_likelihood, settings.mismatch_probability)
    log_prob = torch.where(taken, normalized(log_prob + share * log_likelihood), log_prob)
    healthy = healthy | relocalized
    posterior = Belief(log_prob, center, yaw_center, prior.yaw_step)
    pose, covariance = belief_pose(posterior)
    if settings.noise_model == "held":
        for vehicle in (healthy & ~relocalized).nonzero()[:, 0].tolist():
            if held[vehicle] is None:  # the first frame used in full since the start or since lost
                held[vehicle] = search.held_fit(vehicle, prior, log_likelihood[vehicle])
    health = next_health(health, healthy, relocalized, weak_frames, peak_z, frame_temperature, candidate)
    lost = health.weak_frames >= settings.patience
    health = health._replace(held=tuple(None if gone else one for one, gone in zip(held, lost.tolist(), strict=True)))
    refined = torch.full_like(pose, math.nan)
    if settings.refine:
        refined = search.refined(pose, healthy, refined)
    output = TrackOutput(pose, covariance, healthy, relocalized, best_score, peak_z, lost, refined)
    return posterior, output, health


def check_settings(settings: object) -> TrackerSettings:
    """``settings`` as :class:`~enmi_torch.tracking.TrackerSettings` (its defaults for ``None``), else a TypeError."""
    if settings is None:
        return TrackerSettings()
    if not isinstance(settings, TrackerSettings):
        raise TypeError(f"settings must be a TrackerSettings or None, got {type(settings).__name__}")
    return settings


def check_noise_model(settings: TrackerSettings, score: Score) -> None:
    """Refuse ``noise_model="held"`` with a score that estimates no noise model: there would be nothing to hold."""
    if settings.noise_model == "held" and not score.estimates_noise_model:
        raise ValueError(
            f"noise_model='held' has no effect with score={score!r}: it estimates no noise model from each frame to "
            "hold; drop noise_model, or pass a score that estimates one (ECR())"
        )


def check_reference_map(reference: Tensor) -> None:
    """Raise unless ``reference`` is one real floating map ``(1, 1, Hm, Wm)`` with a cell at least."""
    check_floating("reference", reference)
    check_real_data("reference", reference)
    if reference.ndim != 4 or reference.shape[:2] != (1, 1) or reference.numel() == 0:
        raise ValueError(f"reference must be one map (1, 1, Hm, Wm) or (Hm, Wm), got {tuple(reference.shape)}")


def default_score() -> ECR:
    """The tracker's score when none is given: ``ECR(response="binned", misfit="correlated")``, not ECR's default.

    A filter adds up its frames' evidence, so it needs the evidence's size, not only which placement wins. ECR with
    an independent misfit (its default, and :func:`~enmi_torch.localize`'s) counts every pixel of a changed patch of
    the scene as independent evidence, and the filter then trusts wrong peaks where the scene has changed since the
    map. With the misfit taken as spatially correlated (its excess over the bins' quantisation times the pixels per
    independent misfit, :func:`~enmi_torch.scores.ecr.misfit_extent`) a changed patch counts as one piece of
    evidence. Measured on drives over real photographs of two dates (``docs/choosing_a_score.md``, 6 drives):
    within one cell in 0.500 of the frames against 0.376 with ``ECR()`` (paired -0.124 +- 0.040), lost in 0.236
    against 0.415; on simulated drives ``ECR()`` is ahead by 0.01 to 0.09, so pass ``score=ECR()`` where the scene
    does not change.

    Example:
        >>> default_score() == ECR(response="binned", misfit="correlated")
        True
    """
    return ECR(response="binned", misfit="correlated")


def coasting_noise(motion_noise: Sequence[float] | Tensor, weak_frames: Tensor, coasting: str) -> Tensor:
    """``(B, 3)`` odometry noise of the next prediction after ``weak_frames`` ``(B,)`` frames without a used match.

    ``"linear"``: ``motion_noise * sqrt(2k + 1)``, so that ``k + 1`` predictions in a row add ``(k + 1)^2`` times
    one frame's variance, the spread of a constant bias; ``"random_walk"``: ``motion_noise`` as it is.

    Example:
        >>> coasting_noise((0.5, 0.5, 0.1), torch.tensor([0, 4]), "linear").round(decimals=6).tolist()
        [[0.5, 0.5, 0.1], [1.5, 1.5, 0.3]]
    """
    check_option("coasting", coasting, COASTING)
    noise = check_noise("motion_noise", motion_noise, weak_frames.shape[0]).to(weak_frames.device)
    if coasting == "random_walk":
        return noise
    return noise * (2 * weak_frames.double() + 1).sqrt()[:, None]


def relocalization_gain(fresh: Tensor, window: Tensor) -> Tensor:
    """Nats by which the best of the restarted window's log-likelihood ``fresh`` beats the predicted ``window``'s.

    A jump needs a much better match than the window's (``relocalize_odds``), both at the window's temperature.

    Example:
        >>> relocalization_gain(torch.tensor([3.0, 40.0]), torch.tensor([[31.0, -2.0]])).item()
        9.0
    """
    return fresh.max() - window.max()


def fresh_peak_is_clear(
    peak_z: Tensor,
    temperature: Tensor,
    typical_z: Tensor,
    typical_temperature: Tensor,
    min_peak_z: float,
    z_drop: float,
) -> bool:
    """Whether a relocalization's peak is as clear and as sharp as the recent matches', within ``z_drop``.

    Its robust z-score must reach ``min_peak_z`` and ``z_drop`` times the recent matches' (``typical_z``), its grid
    temperature ``z_drop`` times theirs: a featureless stretch has weak, flat peaks everywhere, and the best of them
    is no place. NaN typical values (no recent match) rule nothing out.

    Example:
        >>> nan = torch.tensor(float("nan"))
        >>> fresh_peak_is_clear(torch.tensor(4.0), torch.tensor(9.0), torch.tensor(12.0), nan, 2.5, 0.3)
        True
        >>> fresh_peak_is_clear(torch.tensor(3.0), torch.tensor(9.0), torch.tensor(12.0), nan, 2.5, 0.3)  # < 3.6
        False
    """
    if not bool(peak_z >= min_peak_z) or bool(peak_z < z_drop * typical_z):
        return False
    return not bool(temperature < z_drop * typical_temperature)


AGREEMENT_CELLS = 2.0  # two wide searches agree within this many cells (and as many yaw bins)


def wide_matches_agree(offset: Tensor, previous: Tensor, yaw_step: float) -> bool:
    """Whether two frames' wide searches found the same place: the relocalization's agreement rule.

    ``offset`` and ``previous`` are ``(3,)`` ``(x, y, yaw)`` of each frame's best wide match relative to its own
    predicted window (NaN: that frame had none). They agree within :data:`AGREEMENT_CELLS` cells along ``x`` and
    along ``y`` and within as many yaw bins of ``yaw_step`` degrees.

    Example:
        >>> wide_matches_agree(torch.tensor([10.0, -3.0, 1.0]), torch.tensor([8.0, -4.5, -1.0]), 1.0)
        True
        >>> wide_matches_agree(torch.tensor([10.0, -3.0, 1.0]), torch.tensor([10.0, -5.5, 1.0]), 1.0)
        False
    """
    if not bool(torch.isfinite(previous).all()):
        return False
    near = bool((offset[:2] - previous[:2]).abs().max() <= AGREEMENT_CELLS)
    return near and bool((offset[2] - previous[2]).abs() <= AGREEMENT_CELLS * yaw_step)


def _restart(belief: Belief, vehicle: int, pose: Tensor) -> Belief:
    """The belief with vehicle ``vehicle``'s window moved to ``pose`` (yaw on the belief's yaw lattice)."""
    center, yaw_center = belief.center.clone(), belief.yaw_center.clone()
    center[vehicle] = torch.stack([pose[1], pose[0]]).round().long().to(center.device)
    steps = ((pose[2].to(yaw_center.device) - yaw_center[vehicle]) / belief.yaw_step).round()
    yaw_center[vehicle] = yaw_center[vehicle] + steps * belief.yaw_step
    return belief._replace(center=center, yaw_center=yaw_center)


def _peak_position(belief: Belief, log_likelihood: Tensor, vehicle: int) -> Tensor:
    """``(2,)`` ``(x, y)`` of the best cell of a vehicle's log-likelihood on the belief's grid."""
    _, rows, cols = log_likelihood.shape[1:]
    rest = int(log_likelihood[vehicle].flatten().argmax()) % (rows * cols)
    row, col = divmod(rest, cols)
    radius_y, radius_x = belief.radius
    center = belief.center[vehicle].double()
    return torch.stack([center[1] + col - radius_x, center[0] + row - radius_y])
