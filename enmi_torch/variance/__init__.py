"""Per-pixel noise variance maps for ENMI: the interface and its implementations."""

from enmi_torch.variance.base import ConstantVariance, VarianceModel
from enmi_torch.variance.empirical import EmpiricalVariance, empirical_variance
from enmi_torch.variance.learned import (
    LearnedVariance,
    gaussian_nll,
    perspective_basis,
    radial_basis,
    smoothness_penalty,
)
from enmi_torch.variance.perspective import (
    PerspectiveVariance,
    homography_variance,
    perspective_cell_areas,
    perspective_variance,
)

__all__ = [
    "ConstantVariance",
    "EmpiricalVariance",
    "LearnedVariance",
    "PerspectiveVariance",
    "VarianceModel",
    "empirical_variance",
    "gaussian_nll",
    "homography_variance",
    "perspective_basis",
    "perspective_cell_areas",
    "perspective_variance",
    "radial_basis",
    "smoothness_penalty",
]
