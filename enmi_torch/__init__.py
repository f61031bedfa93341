"""enmi_torch: noise-aware (enhanced) normalized mutual information for image matching and localization.

The top level holds what a user needs: the scores, the losses, the variance models, the road camera and its ground
grid, localization, registration and tracking. The functions behind the scores and losses (values, surfaces,
histograms, bin weights) are in :mod:`enmi_torch.functional`; everything else is imported from its module.

The names are imported on first use (as scikit-image's and SciPy's top levels do), so that ``import enmi_torch``
and the commands' ``--help`` do not import torch until something needs it.
"""

import importlib
import warnings

# Where each public name lives.
_SOURCES = {
    "ECR": "enmi_torch.scores",
    "ENMI": "enmi_torch.scores",
    "Mixture": "enmi_torch.scores",
    "NCC": "enmi_torch.scores",
    "NMI": "enmi_torch.scores",
    "ECRLoss": "enmi_torch.losses",
    "ENMILoss": "enmi_torch.losses",
    "NMILoss": "enmi_torch.losses",
    "ScoreLoss": "enmi_torch.losses",
    "ConstantVariance": "enmi_torch.variance",
    "EmpiricalVariance": "enmi_torch.variance",
    "LearnedVariance": "enmi_torch.variance",
    "PerspectiveVariance": "enmi_torch.variance",
    "RoadCamera": "enmi_torch.geometry.camera",
    "GroundGrid": "enmi_torch.geometry.rectify",
    "rectify": "enmi_torch.geometry.rectify",
    "unrectify": "enmi_torch.geometry.rectify",
    "Localization": "enmi_torch.localization",
    "localize": "enmi_torch.localization",
    "Registration": "enmi_torch.registration",
    "register": "enmi_torch.registration",
    "Tracker": "enmi_torch.tracking",
    "TrackerSettings": "enmi_torch.tracking",
}

# Submodules reachable as attributes (``enmi_torch.functional``), imported on first use too.
_SUBMODULES = ("functional",)

# Names that left the top level, and the module that holds them now: still importable from ``enmi_torch`` until
# 0.3, with a DeprecationWarning naming the new place.
_MOVED = {
    **dict.fromkeys(
        (
            "bin_centers",
            "bin_edges",
            "ecr",
            "ecr_from_bin_sums",
            "ecr_loss",
            "ecr_surface",
            "enmi",
            "enmi_loss",
            "enmi_surface",
            "entropies",
            "gaussian_log_prior",
            "joint_histogram",
            "likelihood_weights",
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
            "truncated_likelihood_weights",
        ),
        "enmi_torch.functional",
    ),
    **dict.fromkeys(
        ("MemoryBudgetError", "get_memory_budget", "memory_budget", "set_memory_budget"), "enmi_torch.utils.budget"
    ),
    "value_checks": "enmi_torch.utils.checks",
    "Localizer": "enmi_torch.localization",
    "NoCandidateError": "enmi_torch.localization",
    "MixtureLoss": "enmi_torch.losses",
    "Surface": "enmi_torch.placement",
    "registration_score": "enmi_torch.registration",
    "warp_reference": "enmi_torch.registration",
    "Score": "enmi_torch.scores",
    "as_score": "enmi_torch.scores",
    "direct_surface": "enmi_torch.scores",
    "BinSums": "enmi_torch.scores.ecr",
    "Calibration": "enmi_torch.tracking",
    "VarianceModel": "enmi_torch.variance",
    "empirical_variance": "enmi_torch.variance",
    "gaussian_nll": "enmi_torch.variance",
    "perspective_variance": "enmi_torch.variance",
}

__version__ = "0.1.0"

__all__ = [
    "ECR",
    "ENMI",
    "NCC",
    "NMI",
    "ConstantVariance",
    "ECRLoss",
    "ENMILoss",
    "EmpiricalVariance",
    "GroundGrid",
    "LearnedVariance",
    "Localization",
    "Mixture",
    "NMILoss",
    "PerspectiveVariance",
    "Registration",
    "RoadCamera",
    "ScoreLoss",
    "Tracker",
    "TrackerSettings",
    "localize",
    "rectify",
    "register",
    "unrectify",
]


def __getattr__(name: str):
    """Import a public name (or ``functional``) from its module on first use; a moved name with a warning."""
    if name in _SOURCES:
        value = getattr(importlib.import_module(_SOURCES[name]), name)
        globals()[name] = value
        return value
    if name in _SUBMODULES:
        return importlib.import_module(f"{__name__}.{name}")
    if name in _MOVED:
        warnings.warn(
            f"enmi_torch.{name} is deprecated and will be removed in 0.3; use {_MOVED[name]}.{name}",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(importlib.import_module(_MOVED[name]), name)
    raise AttributeError(f"module 'enmi_torch' has no attribute {name!r}")


def __dir__() -> list[str]:
    dunders = {name for name in globals() if name.startswith("__") and name.endswith("__")}
    return sorted(dunders | set(__all__) | set(_SUBMODULES))
