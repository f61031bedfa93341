"""The streaming filter: :class:`Tracker` holds the map, the settings and the running belief, one frame per call.

Each call is one :func:`~enmi_torch.tracking.track_step` on the stored belief.
"""

from __future__ import annotations

import dataclasses

from torch import Tensor, nn

from enmi_torch.scores import Score, as_score
from enmi_torch.tracking.belief import Belief, check_belief_memory, initial_belief
from enmi_torch.tracking.calibration import Calibration, checked_calibration
from enmi_torch.tracking.health import Health
from enmi_torch.tracking.settings import TrackerSettings, refuse_moved_tracker_keywords
from enmi_torch.tracking.step import (
    TrackOutput,
    check_noise_model,
    check_reference_map,
    check_settings,
    default_score,
    track_step,
)
from enmi_torch.utils.checks import check_floating, check_positive_int, check_shifts
from enmi_torch.variance.base import VarianceModel, call_variance

CALIBRATED = ("temperature", "min_peak_z")  # the settings a Calibration sets


class Tracker(nn.Module):
    """A histogram (Bayes) filter over the map: one captured frame and its odometry in, one pose out (streaming).

    It stores the map, the score, the :class:`~enmi_torch.tracking.TrackerSettings` and the running belief, and runs
    :func:`enmi_torch.tracking.track_step` (the function form, one step on an explicit belief) on each frame:
    ``start(pose)`` sets the first pose, then ``tracker(captured, odometry, variance)`` returns a
    :class:`~enmi_torch.tracking.TrackOutput` (``pose``, ``covariance``, ``healthy``, ``lost``, ...).

    It needs no calibration: by default (``temperature="auto"``) each frame's log-likelihood is flattened to the
    belief's bin size (:func:`~enmi_torch.tracking.calibration.grid_temperature`). A frame without a clear peak only
    nudges the belief (``weak_update``); one it cannot use (fully masked, off the map, a peak the prediction rules
    out) is skipped and the belief coasts on the odometry; ``output.lost`` is ``True`` from ``patience`` frames
    without a clear match in a row until a match is used or a relocalization succeeds. How it fares on simulated and
    photographed drives is in the documentation's drive benchmark.

    Args:
        reference: ``(1, 1, Hm, Wm)`` or ``(Hm, Wm)`` map (a non-persistent buffer).
        variance_model: optional :class:`~enmi_torch.variance.VarianceModel` of the captured images' noise.
        settings: the motion noise, likelihood scale, health rules and relocalization search
            (:class:`~enmi_torch.tracking.TrackerSettings`); ``None``: its defaults.
        score: the score of the surfaces, a :class:`~enmi_torch.scores.Score` or its name (see
            :func:`~enmi_torch.localize`); ``None``: the calibration's score by name, else :func:`default_score`
            (ECR with a spatially correlated misfit and the binned response; ECR's own shrunk response, also what
            the name ``"ecr"`` gives, re-reads its ``delta^2`` every frame: :func:`default_score` says what that
            does to the health rules).
        calibration: optional :class:`~enmi_torch.tracking.Calibration`: it sets the settings' ``temperature`` and
            ``min_peak_z`` and, without ``score``, the score by name. Settings that set either away from its default
            as well are refused.
        shifts: belief window radius ``r`` or ``(ry, rx)``.
        yaw_bins: odd number of yaw bins.
        yaw_step: yaw bin spacing in degrees.

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 64, 96, generator=generator) * 256
        >>> from enmi_torch import ECR
        >>> from enmi_torch.tracking import TrackerSettings
        >>> settings = TrackerSettings(motion_noise=(0.3, 0.3, 0.1))
        >>> tracker = Tracker(reference, settings=settings, score=ECR(bins=16), shifts=4, yaw_bins=1)
        >>> tracker.start(torch.tensor([[40.0, 30.0, 0.0]]))
        >>> for x in (42, 44, 46):  # the vehicle drives 2 cells per frame along the map's columns
        ...     output = tracker(reference[..., 22:38, x - 8 : x + 8], torch.tensor([[2.0, 0.0, 0.0]]), 1.0)
        >>> output.pose.round().tolist(), bool(output.healthy[0])
        ([[46.0, 30.0, 0.0]], True)
    """

    @refuse_moved_tracker_keywords
    def __init__(
        self,
        reference: Tensor,
        variance_model: VarianceModel | None = None,
        *,
        settings: TrackerSettings | None = None,
        score: Score | str | None = None,
        calibration: Calibration | None = None,
        shifts: int | tuple[int, int] = 8,
        yaw_bins: int = 5,
        yaw_step: float = 1.0,
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
        settings = check_settings(settings)
        if score is not None:
            score = as_score(score)
        if calibration is not None:
            settings, score = _calibrated(settings, score, calibration)
        self.settings = settings
        self.score = default_score() if score is None else score
        check_noise_model(settings, self.score)
        self.belief: Belief | None = None
        self.health: Health | None = None

    def start(self, pose: Tensor, std: tuple[float, float, float] | None = None) -> None:
        """Start (or restart) the filter at ``(B, 3)`` poses ``(x, y, yaw)``: a flat or Gaussian belief.

        The pose is absolute in the map (x the column, y the row, yaw in degrees), as :func:`~enmi_torch.localize`
        returns it (``tracker.start(localize(...).pose)``) and :func:`~enmi_torch.register` takes it.
        """
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
            score=self.score,
            settings=self.settings,
            health=self.health,
        )
        return output


def _calibrated(settings: TrackerSettings, score: Score | None, calibration: object) -> tuple[TrackerSettings, Score]:
    """The settings with the calibration's temperature and peak threshold, and the score it was fitted for."""
    if not isinstance(calibration, Calibration):
        raise TypeError(f"calibration must be a Calibration or None, got {type(calibration).__name__}")
    calibration = checked_calibration(calibration, "calibration")
    defaults = TrackerSettings()
    overlap = [name for name in CALIBRATED if getattr(settings, name) != getattr(defaults, name)]
    if overlap:
        raise ValueError(
            f"calibration sets {', '.join(CALIBRATED)}, got settings with {', '.join(overlap)} set too: "
            "pass one or the other"
        )
    fitted = calibration.fitted_noise_model
    if settings.noise_model not in (defaults.noise_model, fitted):
        # A log-likelihood's scale depends on how the noise model is read: held, or every frame its own.
        raise ValueError(
            f"calibration was fitted with noise_model={fitted!r}, got settings with noise_model="
            f"{settings.noise_model!r}: leave noise_model out (the calibration sets it), or calibrate with it"
        )
    if score is None:
        score = as_score(calibration.score)
    elif as_score(calibration.score).name != score.name:
        # Its temperature and peak threshold are on that score's scale, not this one's.
        raise ValueError(
            f"calibration was fitted for score {calibration.score!r}, got score={score.name!r}: "
            f"pass score={calibration.score!r} (or leave score out), or calibrate {score.name!r}"
        )
    changes = {name: getattr(calibration, name) for name in CALIBRATED}
    return dataclasses.replace(settings, noise_model=fitted, **changes), score
