"""Tracking a drive: a Bayes (histogram) filter over the pose, one score surface per frame.

Data flow, each module importing only the ones before it: :mod:`~enmi_torch.tracking.belief` (the histogram over
cells and yaw bins: predict, update, read the pose) and :mod:`~enmi_torch.tracking.health` (which frames' matches are
used) → :mod:`~enmi_torch.tracking.calibration` (the likelihood's temperature, the calibration file) →
:mod:`~enmi_torch.tracking.tracker` (one filter step, :func:`track_step`, and the streaming :class:`Tracker`, which
search with :func:`~enmi_torch.localize`).
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
from enmi_torch.tracking.tracker import Tracker, TrackOutput, coasting_noise, default_score, track_step

__all__ = [
    "CHI2_95_2D",
    "Belief",
    "Calibration",
    "Health",
    "TrackOutput",
    "Tracker",
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
