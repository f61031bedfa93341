"""Sequential localization over a drive: a Bayes (histogram) filter on the score surfaces of :func:`localize`.

One step of the filter (:func:`track_step`, :class:`Tracker` for a stream of frames):

* predict: the belief (:mod:`~enmi_torch.tracking.belief`) moves by the odometry and is blurred by its noise, over
  frames without a used match as a random walk (default) or as an odometry bias would (``coasting="linear"``,
  :func:`~enmi_torch.tracking.coasting_noise`);
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
* a window with no candidate at all (off the map, a frame fully masked:
  :class:`~enmi_torch.localization.NoCandidateError` from the search) is a frame without a match: the belief coasts
  on the odometry. ``lost`` says that the filter has gone ``patience`` frames without a match and the wide search
  has not found the vehicle again.

Convention:
    Poses and odometry as in :mod:`~enmi_torch.tracking.belief`; searches run without gradient.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor, nn

from enmi_torch.localization.peak import NoCandidateError
from enmi_torch.localization.search import localize
from enmi_torch.localization.strategy import SearchStrategy
from enmi_torch.registration.refine import check_registration_score, register
from enmi_torch.scores import ECR, Score, as_score
from enmi_torch.tracking.belief import (
    Belief,
    belief_pose,
    check_belief,
    check_belief_memory,
    check_mismatch_probability,
    check_noise,
    finite_floor,
    initial_belief,
    mixed_with_mismatch,
    normalized,
    predict,
)
from enmi_torch.tracking.calibration import Calibration, _checked, grid_temperature
from enmi_torch.tracking.health import (
    Health,
    check_health,
    clearness,
    next_health,
    peak_z_score,
    prediction_surprise,
)
from enmi_torch.utils.checks import (
    check_bool,
    check_floating,
    check_mask_of,
    check_non_negative_int,
    check_option,
    check_positive_int,
    check_positive_number,
    check_real_data,
    check_same_device,
    check_shifts,
)
from enmi_torch.variance.base import VarianceModel, call_variance


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


def track_step(
    belief: Belief,
    captured: Tensor,
    reference: Tensor,
    odometry: Tensor,
    variance: Tensor | float | VarianceModel | None = None,
    captured_mask: Tensor | None = None,
    *,
    motion_noise: Sequence[float] | Tensor = (0.5, 0.5, 0.5),
    coasting: str = "random_walk",
    weak_update: str = "nudge",
    score: Score | str | None = None,
    temperature: float | str = "auto",
    min_peak_z: float = 2.5,
    max_surprise: float = 30.0,
    z_drop: float = 0.3,
    health: Health | None = None,
    patience: int = 2,
    relocalize_shifts: int = 32,
    relocalize_yaw_bins: int = 9,
    coarse_factor: int = 4,
    relocalize_odds: float = 5.0,
    refine: bool = False,
    mismatch_probability: float = 0.0,
) -> tuple[Belief, TrackOutput, Health]:
    """One frame of the filter: predict by ``odometry``, update by the frame's score surface, read the pose.

    Args:
        belief: the belief after the previous frame (:func:`initial_belief` for the first).
        captured: ``(B, 1, h, w)`` captured images on the map's cell grid, one per vehicle.
        reference: ``(1, 1, Hm, Wm)`` the map.
        odometry: ``(B, 3)`` increment since the previous frame (see :func:`predict`).
        variance: the captured images' noise variance for a score that uses one (ECR, ENMI, mixture): a number,
            ``(h, w)``, ``(1 or B, 1, h, w)`` or a :class:`~enmi_torch.variance.VarianceModel`; ``None`` for NMI and
            NCC.
        captured_mask: bool, like ``variance``: ``False`` pixels are unobserved.
        motion_noise: standard deviations of the odometry's error ``(du, dv, dyaw)`` per frame.
        coasting: how the belief widens over frames without a used match. ``"random_walk"`` (default): each
            frame's odometry error independent (the standard deviation grows as the square root of the frames).
            ``"linear"``: the error taken as a bias over the frames coasted (a scale error, a yaw-rate bias), its
            standard deviation growing in proportion to them: after ``k`` such frames the prediction adds
            ``(2k + 1) motion_noise^2``, ``k^2 motion_noise^2`` in all. On the drive benchmark neither wins
            everywhere (``data_tools/README.md``, "Tracking a drive").
        weak_update: what a frame whose peak is too weak to use (``min_peak_z``, ``z_drop``) does to the belief:
            ``"nudge"`` (default) adds its log-likelihood scaled by ``(peak_z / threshold)^2``
            (:func:`~enmi_torch.tracking.health.clearness`), so a run of weak but right frames still holds the
            filter; ``"skip"`` leaves the belief to the odometry. A peak the prediction rules out
            (``max_surprise``) is skipped either way.
        score: the score of the surfaces, a :class:`~enmi_torch.scores.Score` or its name (see
            :func:`~enmi_torch.localize`); ``None`` (default): :func:`default_score`, ECR with a spatially correlated
            misfit and the binned response.
        temperature: ``score * n_valid / temperature`` is the log-likelihood: ``"auto"`` (default) each frame's
            :func:`~enmi_torch.tracking.calibration.grid_temperature` (no sharper than one bin), or a number, e.g.
            from :func:`calibrate_temperature` on surveyed frames.
        min_peak_z: a surface whose best score's robust z-score is below this is no match.
        max_surprise: a peak whose predicted log probability is more than this many nats below the prediction's best
            is no match (the prediction rules it out).
        z_drop: a peak z-score below this fraction of the recent matches' (:class:`Health`) is no match.
        health: the :class:`Health` from the previous step (``None`` at the start).
        patience: relocalize after this many consecutive frames without a match.
        relocalize_shifts: radius in cells of the relocalization search.
        relocalize_yaw_bins: yaw bins (of the belief's spacing) of the relocalization search.
        coarse_factor: pooling factor of the coarse-to-fine relocalization search.
        relocalize_odds: the relocalization moves the belief only if its match beats the window's best by this
            many nats of (tempered) log-likelihood, its peak is as clear and as sharp as the recent matches'
            (``z_drop``) and the previous frame's wide search found the same place (within 2 cells and 2 yaw bins of
            the predicted window), or lands within 1.5 cells of the window's own peak. With the
            ``"auto"`` temperature a clear match's peak stands ~10 nats above no match: 5 nats are odds of ~150 to 1.
        refine: also register each used frame from the posterior pose (``TrackOutput.refined``): ECR or NCC only.
        mismatch_probability: the chance that a frame matched some other place (a changed scene, a repeated
            pattern): the belief takes the frame's likelihood mixed with a flat one
            (:func:`~enmi_torch.tracking.mixed_with_mismatch`), so one frame moves it by at most
            ``log(1 / p)`` nats. ``0`` (default): the likelihood as it is. Over real photographs of two dates 0.05
            loses fewer frames and widens the ellipses; on simulated drives it is within one cell less often
            (``data_tools/README.md``, "Tracking a drive"). A relocalization restarts from the frame's own
            likelihood either way.

    Returns:
        ``(belief, output, health)``: the posterior :class:`Belief`, the :class:`TrackOutput` and the :class:`Health`
        for the next step.
    """
    check_belief(belief)
    score = default_score() if score is None else as_score(score)
    if check_bool("refine", refine):
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
    if isinstance(temperature, str) and temperature != "auto":
        raise ValueError(f"temperature must be 'auto' or a finite number > 0, got {temperature!r}")
    if temperature != "auto":
        temperature = check_positive_number("temperature", temperature)
    check_positive_number("min_peak_z", min_peak_z)
    check_positive_number("max_surprise", max_surprise)
    check_positive_number("relocalize_odds", relocalize_odds)
    check_positive_number("z_drop", z_drop)
    patience = check_positive_int("patience", patience)
    relocalize_shifts = check_non_negative_int("relocalize_shifts", relocalize_shifts)
    relocalize_yaw_bins = check_positive_int("relocalize_yaw_bins", relocalize_yaw_bins)
    check_option("weak_update", weak_update, ("nudge", "skip"))
    mismatch_probability = check_mismatch_probability(mismatch_probability)
    batch = captured.shape[0]
    health = check_health(health, batch, captured.device)
    search = _Searcher(captured, reference, variance, captured_mask, score)
    prior = predict(belief, odometry, coasting_noise(motion_noise, health.weak_frames, coasting))
    raw, best_score, peak_z, frame_temperature = search.window(prior)
    if temperature == "auto":
        # A frame without a clear peak (a featureless stretch) is read at the scale of the recent clear matches.
        typical = health.typical_temperature
        temperature = torch.where(torch.isfinite(typical), torch.fmax(typical, frame_temperature), frame_temperature)
        temperature = torch.where(torch.isfinite(temperature), temperature, 1.0)[:, None, None, None]
    log_likelihood = raw / temperature
    surprise = prediction_surprise(prior.log_prob, log_likelihood)
    weight = clearness(peak_z, surprise, health, min_peak_z, z_drop, max_surprise)
    healthy = weight >= 1
    weak_frames = torch.where(healthy, 0, health.weak_frames + 1)
    relocalized = torch.zeros_like(healthy)
    log_prob = prior.log_prob.clone()
    center, yaw_center = prior.center.clone(), prior.yaw_center.clone()
    candidate = torch.full_like(health.candidate, math.nan)
    for vehicle in (weak_frames >= patience).nonzero()[:, 0].tolist():
        found = search.wide(vehicle, prior, relocalize_shifts, relocalize_yaw_bins, coarse_factor)
        if found is None:
            continue  # nothing to match in the wide window either (off the map): keep coasting
        window_peak = _peak_position(prior, log_likelihood, vehicle)
        if bool((window_peak - found[:2].to(window_peak)).abs().max() <= 1.5) and bool(peak_z[vehicle] >= min_peak_z):
            healthy[vehicle] = True  # the wide search confirms the window's own peak: use the frame
            continue
        # One frame's best match over the wide window is the best of many noisy candidates: jump only where the
        # previous frame's wide search found the same place (relative to the predicted window, within 2 cells and
        # 2 yaw bins). A lone false peak in a noisy stretch no longer moves a filter that was right.
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
        clear = fresh_peak_is_clear(fresh_z[0], fresh_temperature[0], *typical, min_peak_z, z_drop)
        if clear and bool(gain >= relocalize_odds):
            log_prob[vehicle] = normalized(fresh_likelihood)[0]
            center[vehicle], yaw_center[vehicle] = fresh.center[vehicle], fresh.yaw_center[vehicle]
            best_score[vehicle], peak_z[vehicle], relocalized[vehicle] = fresh_score[0], fresh_z[0], True
            frame_temperature[vehicle] = fresh_temperature[0]  # the match the belief restarts from
    # How much of the frame the belief takes: all of a used match (a wide search may have confirmed a weak peak),
    # its clearness of a weak one when nudging, none of a relocalized frame (its belief restarted from it).
    share = torch.where(healthy, 1.0, weight if weak_update == "nudge" else 0.0).masked_fill(relocalized, 0.0)
    taken = (share > 0)[:, None, None, None]
    share = share.to(log_likelihood)[:, None, None, None]
    if mismatch_probability > 0:
        log_likelihood = mixed_with_mismatch(log_likelihood, mismatch_probability)
    log_prob = torch.where(taken, normalized(log_prob + share * log_likelihood), log_prob)
    healthy = healthy | relocalized
    posterior = Belief(log_prob, center, yaw_center, prior.yaw_step)
    pose, covariance = belief_pose(posterior)
    health = next_health(health, healthy, relocalized, weak_frames, peak_z, frame_temperature, candidate)
    lost = health.weak_frames >= patience
    refined = torch.full_like(pose, math.nan)
    if refine:
        refined = search.refined(pose, healthy, refined)
    output = TrackOutput(pose, covariance, healthy, relocalized, best_score, peak_z, lost, refined)
    return posterior, output, health


class Tracker(nn.Module):
    """A histogram (Bayes) filter over the map: one captured frame and its odometry in, one pose out (streaming).

    It stores the map, the settings and the running belief, and runs :func:`enmi_torch.tracking.track_step` (the
    function form, one step on an explicit belief) on each frame: ``start(pose)`` sets the first pose, then
    ``tracker(captured, odometry, variance)`` returns a :class:`~enmi_torch.tracking.TrackOutput` (``pose``,
    ``covariance``, ``healthy``, ``lost``, ...).

    It needs no calibration: by default (``temperature="auto"``) each frame's log-likelihood is flattened to the
    belief's bin size (:func:`~enmi_torch.tracking.calibration.grid_temperature`). A frame without a clear peak only
    nudges the belief (``weak_update``); one it cannot use (fully masked, off the map, a peak the prediction rules
    out) is skipped and the belief coasts on the odometry; ``output.lost`` is ``True`` from ``patience`` frames
    without a clear match in a row until a match is used or a relocalization succeeds.

    Args:
        reference: ``(1, 1, Hm, Wm)`` or ``(Hm, Wm)`` map (a non-persistent buffer).
        variance_model: optional :class:`~enmi_torch.variance.VarianceModel` of the captured images' noise.
        score: the score of the surfaces, a :class:`~enmi_torch.scores.Score` or its name (see
            :func:`~enmi_torch.localize`); ``None``: the calibration's score by name, else :func:`default_score`
            (ECR with a spatially correlated misfit and the binned response; ECR's own shrunk response, also what
            the name ``"ecr"`` gives, re-reads its ``delta^2`` every frame: :func:`default_score` says what that
            does to the health rules).
        calibration: optional :class:`~enmi_torch.tracking.Calibration` (sets ``temperature``, ``min_peak_z``
            and, without ``score``, the score by name).
        shifts: belief window radius ``r`` or ``(ry, rx)``.
        yaw_bins: odd number of yaw bins.
        yaw_step: yaw bin spacing in degrees.
        **settings: the other keyword arguments of :func:`enmi_torch.tracking.track_step` (``motion_noise``,
            ``temperature``, ...).

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 64, 96, generator=generator) * 256
        >>> from enmi_torch import ECR
        >>> tracker = Tracker(reference, score=ECR(bins=16), shifts=4, yaw_bins=1, motion_noise=(0.3, 0.3, 0.1))
        >>> tracker.start(torch.tensor([[40.0, 30.0, 0.0]]))
        >>> for x in (42, 44, 46):  # the vehicle drives 2 cells per frame along the map's columns
        ...     output = tracker(reference[..., 22:38, x - 8 : x + 8], torch.tensor([[2.0, 0.0, 0.0]]), 1.0)
        >>> output.pose.round().tolist(), bool(output.healthy)
        ([[46.0, 30.0, 0.0]], True)
    """

    def __init__(
        self,
        reference: Tensor,
        variance_model: VarianceModel | None = None,
        *,
        score: Score | str | None = None,
        calibration: Calibration | None = None,
        shifts: int | tuple[int, int] = 8,
        yaw_bins: int = 5,
        yaw_step: float = 1.0,
        **settings,
    ) -> None:
        super().__init__()
        check_floating("reference", reference)
        if reference.ndim == 2:
            reference = reference[None, None]
        check_reference_map(reference)
        self.register_buffer("reference", reference, persistent=False)
        if variance_model is not None and not isinstance(variance_model, VarianceModel):
            raise TypeError(f"variance_model must be a VarianceModel or None, got {type(variance_model).__name__}")
        self.variance_model = variance_model
        self.shifts = check_shifts(shifts)
        self.yaw_bins, self.yaw_step = check_positive_int("yaw_bins", yaw_bins), yaw_step
        check_belief_memory(shifts, self.shifts, self.yaw_bins, 1)  # per vehicle; start() checks its batch
        if calibration is not None:
            if not isinstance(calibration, Calibration):
                raise TypeError(f"calibration must be a Calibration or None, got {type(calibration).__name__}")
            settings = {**_checked(calibration, "calibration")._asdict(), **settings}
        if score is not None:
            settings["score"] = as_score(score)
            if calibration is not None and as_score(calibration.score).name != settings["score"].name:
                # Its temperature and peak threshold are on that score's scale, not this one's.
                raise ValueError(
                    f"calibration was fitted for score {calibration.score!r}, got score={settings['score'].name!r}: "
                    f"pass score={calibration.score!r} (or leave score out), or calibrate {settings['score'].name!r}"
                )
        unknown = set(settings) - set(_STEP_SETTINGS)
        if unknown:
            raise TypeError(f"Tracker got unknown setting(s) {sorted(unknown)}; known: {list(_STEP_SETTINGS)}")
        self.settings = settings
        self.belief: Belief | None = None
        self.health: Health | None = None

    def start(self, pose: Tensor, std: tuple[float, float, float] | None = None) -> None:
        """Start (or restart) the filter at ``(B, 3)`` poses ``(x, y, yaw)``: a flat or Gaussian belief."""
        self.belief = initial_belief(pose, shifts=self.shifts, yaw_bins=self.yaw_bins, yaw_step=self.yaw_step, std=std)
        self.health = None

    def forward(
        self,
        captured: Tensor,
        odometry: Tensor,
        variance: Tensor | float | None = None,
        captured_mask: Tensor | None = None,
    ) -> TrackOutput:
        """One frame in, one pose out: :func:`track_step` on the stored belief, which it replaces."""
        if self.belief is None:
            raise RuntimeError("Tracker has no belief yet: call start(pose) first")
        variance = call_variance("Tracker", variance, self.variance_model)
        self.belief, output, self.health = track_step(
            self.belief,
            captured,
            self.reference,
            odometry,
            variance,
            captured_mask,
            health=self.health,
            **self.settings,
        )
        return output


_STEP_SETTINGS = (
    "motion_noise",
    "coasting",
    "weak_update",
    "score",
    "temperature",
    "min_peak_z",
    "max_surprise",
    "z_drop",
    "patience",
    "relocalize_shifts",
    "relocalize_yaw_bins",
    "coarse_factor",
    "relocalize_odds",
    "refine",
    "mismatch_probability",
)


def check_reference_map(reference: Tensor) -> None:
    """Raise unless ``reference`` is one real floating map ``(1, 1, Hm, Wm)`` with a cell at least."""
    check_floating("reference", reference)
    check_real_data("reference", reference)
    if reference.ndim != 4 or reference.shape[:2] != (1, 1) or reference.numel() == 0:
        raise ValueError(f"reference must be one map (1, 1, Hm, Wm) or (Hm, Wm), got {tuple(reference.shape)}")


def default_score() -> ECR:
    """The tracker's score when none is given: ``ECR(response="binned", misfit="correlated")``.

    The binned response, not ECR's shrunk default: the shrunk response reads its ``delta^2`` from each frame, and the
    spread of a frame's surface about its peak changes with it by orders of magnitude on clean frames (a noiseless
    drive's peak z-scores went from 16,000 to 480 from one frame to the next), which the health rules, comparing a
    frame's peak with the recent ones', take for a lost match.

    A filter adds up its frames' evidence, so it needs the evidence's size, not only which placement wins. ECR with
    an independent misfit (its default, and :func:`~enmi_torch.localize`'s) counts every pixel of a changed patch of
    the scene as independent evidence: on drives over real photographs of two dates the filter then trusts wrong
    peaks and loses the vehicle in 40 % of frames. With the misfit taken as spatially correlated (its excess over the
    bins' quantisation times the pixels per independent misfit, :func:`~enmi_torch.scores.ecr.misfit_extent`) it
    loses 23-25 %; on simulated drives it is within one cell somewhat less often (``data_tools/README.md``,
    "Tracking a drive").

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
    check_option("coasting", coasting, ("linear", "random_walk"))
    noise = check_noise("motion_noise", motion_noise, weak_frames.shape[0]).to(weak_frames.device)
    if coasting == "random_walk":
        return noise
    return noise * (2 * weak_frames.double() + 1).sqrt()[:, None]


class _Searcher:
    """Score surfaces of the captured images over a belief's window and over the wide relocalization window."""

    def __init__(self, captured, reference, variance, captured_mask, score: Score) -> None:
        self.captured, self.reference, self.variance, self.mask = captured, reference, variance, captured_mask
        self.score = score
        valid = torch.ones_like(captured, dtype=torch.bool)
        if captured_mask is not None:
            valid = valid & self._per_vehicle(captured_mask, slice(None)).expand_as(captured)
        if isinstance(variance, VarianceModel):
            model_mask = variance.valid_mask(captured)
            if model_mask is not None:
                valid = valid & model_mask
        self.valid_count = valid.flatten(1).sum(1).double()

    def _per_vehicle(self, values, vehicle):
        """``values`` for vehicle(s) ``vehicle``: a per-vehicle batch is sliced, a shared one kept."""
        if isinstance(values, Tensor) and values.ndim == 4 and values.shape[0] > 1:
            return values[vehicle]
        return values

    def _localize(self, vehicle: int, center: Tensor, yaws: list[float], shifts: int | tuple[int, int], **options):
        """The one call of :func:`~enmi_torch.localize` (its mask keyword in one place)."""
        return localize(
            self.captured[vehicle : vehicle + 1],
            self.reference,
            self._per_vehicle(self.variance, slice(vehicle, vehicle + 1)),
            shifts=shifts,
            center=center.reshape(1, 2),
            yaws=yaws,
            captured_mask=self._per_vehicle(self.mask, slice(vehicle, vehicle + 1)),
            score=self.score,
            **options,
        )

    def window(self, belief: Belief, only: int | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Raw log-likelihood, best score, its robust z-score and grid temperature over the belief's window.

        They are ``score * n_valid`` ``(B, Y, Sy, Sx)`` and ``(B,)`` each (:func:`grid_temperature`).
        A vehicle whose window has no candidate gets a flat log-likelihood (zeros) and NaN for the rest.
        """
        vehicles = range(belief.log_prob.shape[0]) if only is None else [only]
        likelihoods, scores, z_scores, temperatures = [], [], [], []
        yaws = belief.yaws()
        for vehicle in vehicles:
            try:
                if not bool(self.valid_count[vehicle] > 0):
                    raise NoCandidateError(f"captured image {vehicle} has no valid pixel")  # a frame fully masked
                found = self._localize(vehicle, belief.center[vehicle], yaws[vehicle].tolist(), belief.radius)
            except NoCandidateError:
                nothing = torch.tensor(math.nan, dtype=torch.float64, device=belief.log_prob.device)
                likelihoods.append(torch.zeros_like(belief.log_prob[vehicle]))
                scores.append(nothing)
                z_scores.append(nothing)
                temperatures.append(nothing)
                continue
            surface = finite_floor(found.surface[0].double())
            log_likelihood = surface * self.valid_count[vehicle].to(surface.device)
            likelihoods.append(log_likelihood)
            scores.append(surface.max())
            z_scores.append(peak_z_score(log_likelihood, min_spread=1.0))
            temperatures.append(grid_temperature(log_likelihood[None])[0])
        return torch.stack(likelihoods), torch.stack(scores), torch.stack(z_scores), torch.stack(temperatures)

    def refined(self, pose: Tensor, used: Tensor, refined: Tensor) -> Tensor:
        """``refined`` with the used vehicles' rows replaced by :func:`register` from ``pose`` (one batch)."""
        rows = used.nonzero()[:, 0]
        if len(rows) == 0:
            return refined
        found = register(
            self.captured[rows],
            self.reference,
            self._per_vehicle(self.variance, rows),
            pose=pose[rows].to(torch.float64),
            score=self.score,
            captured_mask=self._per_vehicle(self.mask, rows),
            margin=1.0,
        )
        refined[rows] = found.pose.to(refined.dtype)
        return refined

    def wide(self, vehicle: int, belief: Belief, shifts: int, yaw_bins: int, coarse_factor: int) -> Tensor | None:
        """``(3,)`` pose ``(x, y, yaw)`` of the best match over the wide window around the belief's centre.

        ``None`` where the wide window has no candidate either.
        """
        offsets = (torch.arange(yaw_bins, dtype=torch.float64) - yaw_bins // 2) * belief.yaw_step
        yaws = (belief.yaw_center[vehicle].cpu() + offsets).tolist()
        if not bool(self.valid_count[vehicle] > 0):
            return None
        try:
            found = self._localize(
                vehicle,
                belief.center[vehicle],
                yaws,
                shifts,
                search=SearchStrategy(coarse_factor=coarse_factor),
                min_overlap=0.5,
            )
        except NoCandidateError:
            return None
        pose = found.pose[0].double()
        center = belief.center[vehicle].double()
        return torch.stack([center[1] + pose[0], center[0] + pose[1], pose[2]])


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
