"""Per-pixel noise variance maps for ENMI: the interface and its implementations."""

from enmi_torch.variance.base import ConstantVariance, VarianceModel
from enmi_torch.variance.perspective import (
    PerspectiveVariance,
    homography_variance,
    perspective_cell_areas,
    perspective_variance,
)

__all__ = [
    "ConstantVariance",
    "PerspectiveVariance",
    "VarianceModel",
    "homography_variance",
    "perspective_cell_areas",
    "perspective_variance",
]
