"""Tracking a drive: a Bayes (histogram) filter over the pose, one score surface per frame.

Data flow, each module importing only the ones before it: :mod:`~enmi_torch.tracking.belief` (the histogram over
cells and yaw bins: predict, update, read the pose) and :mod:`~enmi_torch.tracking.health` (which frames' matches are
used) → :mod:`~enmi_torch.tracking.calibration` (the likelihood's temperature, the calibration file) →
:mod:`~enmi_torch.tracking.settings` (the filter's settings, :class:`TrackerSettings`) →
:mod:`~enmi_torch.tracking.search` (a frame's score surfaces, searched with :func:`~enmi_torch.localize`) →
:mod:`~enmi_torch.tracking.step` (one filter step, :func:`track_step`) → :mod:`~enmi_torch.tracking.tracker` (the
streaming :class:`Tracker`).
"""

from enmi_torch.tracking.belief import (
    CHI2_95_2D,
    Belief,
    belief_pose,
    initial_belief,
    mixed_with_mismatch,
    predict,
    update,
)
from enmi_torch.tracking.calibration import Calibration, calibrate_temperature, grid_temperature
from enmi_torch.tracking.health import Health
from enmi_torch.tracking.settings import TrackerSettings
from enmi_torch.tracking.step import TrackOutput, coasting_noise, default_score, track_step
from enmi_torch.tracking.tracker import Tracker

__all__ = [
    "CHI2_95_2D",
    "Belief",
    "Calibration",
    "Health",
    "TrackOutput",
    "Tracker",
    "TrackerSettings",
    "belief_pose",
    "calibrate_temperature",
    "coasting_noise",
    "default_score",
    "grid_temperature",
    "initial_belief",
    "mixed_with_mismatch",
    "predict",
    "track_step",
    "update",
]
