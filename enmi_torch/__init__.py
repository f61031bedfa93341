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
from enmi_torch.geometry.camera import RoadCamera
from enmi_torch.geometry.rectify import GroundGrid, rectify, unrectify
from enmi_torch.histogram import joint_histogram
from enmi_torch.information import entropies, nmi_from_joint_histogram
from enmi_torch.localization.peak import Localization, NoCandidateError
from enmi_torch.localization.search import Localizer, localize
from enmi_torch.losses import ECRLoss, ENMILoss, MixtureLoss, NMILoss, ScoreLoss
from enmi_torch.placement import Surface
from enmi_torch.registration import Registration, register, registration_score, warp_reference
from enmi_torch.scores import ECR, ENMI, NCC, NMI, Mixture, Score, as_score, direct_surface
from enmi_torch.scores.ecr import BinSums, ecr, ecr_from_bin_sums, ecr_loss, ecr_surface
from enmi_torch.scores.enmi import enmi, enmi_loss, enmi_surface
from enmi_torch.scores.mixture import mixture_information, mixture_loss, mixture_surface
from enmi_torch.scores.ncc import ncc, ncc_loss, ncc_surface
from enmi_torch.scores.nmi import nmi, nmi_loss, nmi_surface
from enmi_torch.tracking import Calibration, Tracker
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
    "ECR",
    "ENMI",
    "NCC",
    "NMI",
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
    "Mixture",
    "MixtureLoss",
    "NMILoss",
    "NoCandidateError",
    "PerspectiveVariance",
    "Registration",
    "RoadCamera",
    "Score",
    "ScoreLoss",
    "Surface",
    "Tracker",
    "VarianceModel",
    "as_score",
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
    "ncc",
    "ncc_loss",
    "ncc_surface",
    "nmi",
    "nmi_from_joint_histogram",
    "nmi_loss",
    "nmi_surface",
    "parzen_weights",
    "perspective_variance",
    "rectify",
    "register",
    "registration_score",
    "set_memory_budget",
    "truncated_likelihood_weights",
    "unrectify",
    "value_checks",
    "warp_reference",
]
