"""The functions behind the score objects and the losses: values, surfaces, losses, histograms and bin weights.

What :class:`~enmi_torch.NMI`, :class:`~enmi_torch.ENMI`, :class:`~enmi_torch.ECR`, :class:`~enmi_torch.NCC` and
:class:`~enmi_torch.Mixture` call, as plain functions of tensors (kornia's ``kornia.losses.ssim_loss`` beside
``SSIMLoss``): each family's value on aligned pairs (``nmi``, ``enmi``, ``ecr``, ``ncc``, ``mixture_information``),
its surface over every placement (``*_surface``) and its loss (``*_loss``, the same computation as the score's
``.loss`` and the loss modules); the joint histogram and its information (streaming evaluation: counts summed over
batches and processes, then scored); ECR from streamed bin sums; and the bin weights a pixel gives the bins.

Example:
    >>> from enmi_torch import functional as F
    >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
    >>> F.nmi(image, image, bins=4, kernel="hard"), F.nmi_loss(image, image.mT, bins=4)
    (tensor([2.]), tensor(0.9927))
"""

from enmi_torch.binning import (
    bin_centers,
    bin_edges,
    gaussian_log_prior,
    likelihood_weights,
    parzen_weights,
    truncated_likelihood_weights,
)
from enmi_torch.histogram import joint_histogram
from enmi_torch.information import entropies, nmi_from_joint_histogram
from enmi_torch.scores.ecr import ecr, ecr_from_bin_sums, ecr_loss, ecr_surface
from enmi_torch.scores.enmi import enmi, enmi_loss, enmi_surface
from enmi_torch.scores.mixture import mixture_information, mixture_loss, mixture_surface
from enmi_torch.scores.ncc import ncc, ncc_loss, ncc_surface
from enmi_torch.scores.nmi import nmi, nmi_loss, nmi_surface

__all__ = [
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
]
