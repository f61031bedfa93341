"""The filter's settings as one object: motion, likelihood scale, health rules, relocalization search.

:class:`TrackerSettings` is what :class:`~enmi_torch.tracking.Tracker` and
:func:`~enmi_torch.tracking.track_step` take besides the map, the frame and the score; it checks each field once,
when it is made.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

from torch import Tensor

from enmi_torch.localization.strategy import MOVED_TO_SCORE
from enmi_torch.tracking.belief import check_mismatch_probability
from enmi_torch.utils.checks import (
    check_bool,
    check_non_negative_int,
    check_option,
    check_positive_int,
    check_positive_number,
)
from enmi_torch.utils.options import MovedKeywords, refuse_moved_keywords

COASTING = ("linear", "random_walk")
WEAK_UPDATES = ("nudge", "skip")
NOISE_MODELS = ("held", "per_frame")


@dataclass(frozen=True)
class TrackerSettings:
    """How the filter predicts, weighs a frame, judges its health and searches when it has lost the vehicle.

    Every field is checked when the settings are made; a wrong one raises naming the field, what it expects and what
    it got. :func:`dataclasses.replace` makes a changed copy (checked again).

    Attributes:
        motion_noise: standard deviations of the odometry's error ``(du, dv, dyaw)`` per frame, or one such row per
            vehicle (``(B, 3)``, a tensor or nested sequences); kept as tuples of floats.
        coasting: how the belief widens over frames without a used match. ``"random_walk"`` (default): each frame's
            odometry error independent (the standard deviation grows as the square root of the frames).
            ``"linear"``: the error taken as a bias over the frames coasted (a scale error, a yaw-rate bias), its
            standard deviation growing in proportion to them: after ``k`` such frames the prediction adds
            ``(2k + 1) motion_noise^2``, ``k^2 motion_noise^2`` in all (:func:`~enmi_torch.tracking.coasting_noise`).
        weak_update: what a frame whose peak is too weak to use (``min_peak_z``, ``z_drop``) does to the belief:
            ``"nudge"`` (default) adds its log-likelihood scaled by ``(peak_z / threshold)^2``
            (:func:`~enmi_torch.tracking.health.clearness`), so a run of weak but right frames still holds the
            filter; ``"skip"`` leaves the belief to the odometry. A peak the prediction rules out
            (``max_surprise``) is skipped either way.
        temperature: ``score * n_valid / temperature`` is the log-likelihood: ``"auto"`` (default) each frame's
            :func:`~enmi_torch.tracking.calibration.grid_temperature` (no sharper than one bin), or a number, e.g.
            from :func:`~enmi_torch.tracking.calibrate_temperature` on surveyed frames.
        noise_model: how a score that estimates a noise model from each pair (ECR's ``tau^2`` and ``delta^2``) reads
            it. ``"per_frame"`` (default): every frame's surface estimates its own, at its first pass's peak.
            ``"held"``: read on the aligned pair at the peak of the first frame the tracker uses in full and held
            fixed over the frames after it (:meth:`~enmi_torch.scores.Score.held_fit`: for ECR
            ``score.replace(model_variance=tau2, response_variance=delta2)``), so that every frame's surface is one
            likelihood on one scale, exact on each aligned pair (no finalist stage), at about half the time per frame;
            read again at the first frame used after the tracker is lost, and at a relocalization's peak. On the
            drives (``docs/choosing_a_score.md``) the two tie within one standard error but for one simulated drive
            where the held model drifted, hence the default. ``"held"`` is refused with a score that estimates no noise
            model (:attr:`~enmi_torch.scores.Score.estimates_noise_model`: NMI, NCC, ECR with both fixed).
        min_peak_z: a surface whose best score's robust z-score is below this is no match.
        max_surprise: a peak whose predicted log probability is more than this many nats below the prediction's best
            is no match (the prediction rules it out).
        z_drop: a peak z-score below this fraction (``0 < z_drop <= 1``) of the recent matches'
            (:class:`~enmi_torch.tracking.Health`) is no match.
        patience: relocalize after this many consecutive frames without a match.
        relocalize_shifts: radius in cells of the relocalization search.
        relocalize_yaw_bins: yaw bins (of the belief's spacing) of the relocalization search.
        coarse_factor: pooling factor of the coarse-to-fine relocalization search.
        relocalize_odds: the relocalization moves the belief only if its match beats the window's best by this
            many nats of (tempered) log-likelihood, its peak is as clear and as sharp as the recent matches'
            (``z_drop``) and the previous frame's wide search found the same place (within 2 cells and 2 yaw bins of
            the predicted window), or lands within 1.5 cells of the window's own peak. With the ``"auto"``
            temperature a clear match's peak stands about 10 nats above no match: 5 nats are odds of about 150 to 1.
        refine: also register each used frame from the posterior pose (``TrackOutput.refined``): ECR or NCC only.
        mismatch_probability: the chance that a frame matched some other place (a changed scene, a repeated
            pattern): the belief takes the frame's likelihood mixed with a flat one
            (:func:`~enmi_torch.tracking.mixed_with_mismatch`), so one frame moves it by at most ``log(1 / p)``
            nats. ``0`` (default): the likelihood as it is. A relocalization restarts from the frame's own
            likelihood either way.

    Example:
        >>> settings = TrackerSettings(motion_noise=(0.5, 0.5, 0.3), mismatch_probability=0.05)
        >>> settings.motion_noise, settings.temperature, settings.patience
        ((0.5, 0.5, 0.3), 'auto', 2)
        >>> TrackerSettings(patience=0)
        Traceback (most recent call last):
        ...
        ValueError: patience must be an int >= 1, got 0
    """

    motion_noise: tuple[float, ...] | tuple[tuple[float, ...], ...] = (0.5, 0.5, 0.5)
    coasting: str = "random_walk"
    weak_update: str = "nudge"
    temperature: float | str = "auto"
    noise_model: str = "per_frame"
    min_peak_z: float = 2.5
    max_surprise: float = 30.0
    z_drop: float = 0.3
    patience: int = 2
    relocalize_shifts: int = 32
    relocalize_yaw_bins: int = 9
    coarse_factor: int = 4
    relocalize_odds: float = 5.0
    refine: bool = False
    mismatch_probability: float = 0.0

    def __post_init__(self) -> None:
        checked = {
            "motion_noise": check_motion_noise(self.motion_noise),
            "coasting": check_option("coasting", self.coasting, COASTING),
            "weak_update": check_option("weak_update", self.weak_update, WEAK_UPDATES),
            "temperature": check_temperature(self.temperature),
            "noise_model": check_option("noise_model", self.noise_model, NOISE_MODELS),
            "min_peak_z": check_positive_number("min_peak_z", self.min_peak_z),
            "max_surprise": check_positive_number("max_surprise", self.max_surprise),
            "z_drop": check_z_drop(self.z_drop),
            "patience": check_positive_int("patience", self.patience),
            "relocalize_shifts": check_non_negative_int("relocalize_shifts", self.relocalize_shifts),
            "relocalize_yaw_bins": check_positive_int("relocalize_yaw_bins", self.relocalize_yaw_bins),
            "coarse_factor": check_positive_int("coarse_factor", self.coarse_factor),
            "relocalize_odds": check_positive_number("relocalize_odds", self.relocalize_odds),
            "refine": check_bool("refine", self.refine),
            "mismatch_probability": check_mismatch_probability(self.mismatch_probability),
        }
        for name, value in checked.items():
            object.__setattr__(self, name, value)  # frozen: the checked, normalised value

    def replace(self, **changes: object) -> TrackerSettings:
        """A copy with ``changes`` (field names), checked like a new one.

        Example:
            >>> TrackerSettings().replace(temperature=10).temperature
            10.0
        """
        return dataclasses.replace(self, **changes)


def check_z_drop(z_drop: object) -> float:
    """``z_drop`` as a float in ``(0, 1]`` (a fraction of the recent matches' peak z-score), else a ValueError."""
    value = check_positive_number("z_drop", z_drop)
    if value > 1:
        raise ValueError(
            f"z_drop must be a fraction in (0, 1] of the recent matches' peak z-score, got {z_drop!r}: a larger one "
            "would call a peak as clear as the recent ones no match"
        )
    return value


def check_temperature(temperature: object) -> float | str:
    """``"auto"`` or the temperature as a float > 0, else a ValueError naming ``temperature``."""
    if isinstance(temperature, str):
        if temperature != "auto":
            raise ValueError(f"temperature must be 'auto' or a finite number > 0, got {temperature!r}")
        return temperature
    return check_positive_number("temperature", temperature)


def check_motion_noise(noise: object) -> tuple[float, ...] | tuple[tuple[float, ...], ...]:
    """Three standard deviations ``>= 0`` as a tuple, or ``(B, 3)`` of them as a tuple of rows; else a ValueError."""
    values = noise.tolist() if isinstance(noise, Tensor) else noise
    expected = "motion_noise must be three standard deviations >= 0 (du, dv, dyaw) or (B, 3) of them"
    if isinstance(values, (str, bytes)) or not isinstance(values, Sequence):
        raise ValueError(f"{expected}, got {noise!r}")
    rows = values if len(values) and all(isinstance(row, Sequence) for row in values) else [values]
    for row in rows:
        if (
            isinstance(row, (str, bytes))
            or len(row) != 3
            or not all(isinstance(value, (int, float)) and not isinstance(value, bool) for value in row)
            or not all(math.isfinite(value) and value >= 0 for value in row)
        ):
            raise ValueError(f"{expected}, got {noise!r}")
    floats = tuple(tuple(float(value) for value in row) for row in rows)
    return floats if rows is values else floats[0]


# The keywords Tracker and track_step took before 0.2: the settings' fields (all of them) and the score's options.
MOVED_TO_SETTINGS = MovedKeywords(
    tuple(field.name for field in fields(TrackerSettings)), "settings", "TrackerSettings", "enmi_torch.TrackerSettings"
)
refuse_moved_tracker_keywords = refuse_moved_keywords(MOVED_TO_SETTINGS, MOVED_TO_SCORE)
