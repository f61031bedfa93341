"""Localization: score surfaces over every placement, the pose of one frame, its sub-cell peak, the command line.

Data flow, each module importing only the ones before it: :mod:`~enmi_torch.localization.surface` (every shift at
once, by FFT) and :mod:`~enmi_torch.localization.mixture_surface` → :mod:`~enmi_torch.localization.peak` (the
:class:`Localization` result: sub-cell peak, covariance, margin) → :mod:`~enmi_torch.localization.search` (shifts x
yaws, coarse-to-fine: :func:`localize`, :class:`Localizer`) → :mod:`~enmi_torch.localization.track` (a drive: the
histogram filter :class:`Tracker`) and :mod:`~enmi_torch.localization.cli` (``enmi-localize``).
"""

from enmi_torch.localization.mixture_surface import direct_mixture_surface, mixture_surface
from enmi_torch.localization.peak import Localization
from enmi_torch.localization.search import Localizer, localize
from enmi_torch.localization.surface import (
    Surface,
    direct_surface,
    ecr_surface,
    enmi_surface,
    ncc_surface,
    nmi_surface,
)
from enmi_torch.localization.track import Belief, Calibration, Tracker, TrackOutput, calibrate_temperature

__all__ = [
    "Belief",
    "Calibration",
    "Localization",
    "Localizer",
    "Surface",
    "TrackOutput",
    "Tracker",
    "calibrate_temperature",
    "direct_mixture_surface",
    "direct_surface",
    "ecr_surface",
    "enmi_surface",
    "localize",
    "mixture_surface",
    "ncc_surface",
    "nmi_surface",
]
