"""enmi_torch: noise-aware (enhanced) normalized mutual information for image matching and localization."""

from enmi_torch._budget import MemoryBudgetError, get_memory_budget, memory_budget, set_memory_budget
from enmi_torch._checks import value_checks
from enmi_torch.binning import (
    bin_centers,
    bin_edges,
    gaussian_log_prior,
    likelihood_weights,
    parzen_weights,
    truncated_likelihood_weights,
)
from enmi_torch.correlation_ratio import BinSums, ecr, ecr_from_bin_sums
from enmi_torch.geometry.camera import RoadCamera
from enmi_torch.geometry.rectify import GroundGrid, rectify, unrectify
from enmi_torch.histogram import joint_histogram
from enmi_torch.information import enmi, entropies, nmi, nmi_from_joint_histogram
from enmi_torch.localization.mixture_surface import mixture_surface
from enmi_torch.localization.peak import Localization
from enmi_torch.localization.search import Localizer, localize
from enmi_torch.localization.surface import Surface, direct_surface, ecr_surface, enmi_surface, ncc_surface, nmi_surface
from enmi_torch.localization.track import Calibration, Tracker
from enmi_torch.losses import ECRLoss, ENMILoss, MixtureLoss, NMILoss, ecr_loss, enmi_loss, mixture_loss, nmi_loss
from enmi_torch.mixture import mixture_information
from enmi_torch.variance import (
    ConstantVariance,
    EmpiricalVariance,
    LearnedVariance,
    PerspectiveVariance,
    VarianceModel,
    empirical_variance,
    gaussian_nll,
    perspective_variance,
)

__version__ = "0.1.0"

__all__ = [
    "BinSums",
    "Calibration",
    "ConstantVariance",
    "ECRLoss",
    "ENMILoss",
    "EmpiricalVariance",
    "GroundGrid",
    "LearnedVariance",
    "Localization",
    "Localizer",
    "MemoryBudgetError",
    "MixtureLoss",
    "NMILoss",
    "PerspectiveVariance",
    "RoadCamera",
    "Surface",
    "Tracker",
    "VarianceModel",
    "bin_centers",
    "bin_edges",
    "direct_surface",
    "ecr",
    "ecr_from_bin_sums",
    "ecr_loss",
    "ecr_surface",
    "empirical_variance",
    "enmi",
    "enmi_loss",
    "enmi_surface",
    "entropies",
    "gaussian_log_prior",
    "gaussian_nll",
    "get_memory_budget",
    "joint_histogram",
    "likelihood_weights",
    "localize",
    "memory_budget",
    "mixture_information",
    "mixture_loss",
    "mixture_surface",
    "ncc_surface",
    "nmi",
    "nmi_from_joint_histogram",
    "nmi_loss",
    "nmi_surface",
    "parzen_weights",
    "perspective_variance",
    "rectify",
    "set_memory_budget",
    "truncated_likelihood_weights",
    "unrectify",
    "value_checks",
]
