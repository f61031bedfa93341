"""Scores of a captured image against a reference, one family per file, each an object and its functions.

:class:`~enmi_torch.scores.base.Score` (base class, :func:`~enmi_torch.scores.base.as_score`,
:func:`~enmi_torch.scores.base.direct_surface`) → the families :class:`ECR` (:mod:`~enmi_torch.scores.ecr`, with
:mod:`~enmi_torch.scores.ecr_statistics`, :mod:`~enmi_torch.scores.ecr_model_variance`,
:mod:`~enmi_torch.scores.ecr_placements` and :mod:`~enmi_torch.scores.shrunk_response`), :class:`ENMI`
(:mod:`~enmi_torch.scores.enmi`), :class:`NMI` (:mod:`~enmi_torch.scores.nmi`), :class:`NCC`
(:mod:`~enmi_torch.scores.ncc`) and :class:`Mixture` (:mod:`~enmi_torch.scores.mixture`, whose surface ranks
placements by ECR's). Each family's file owns the value on aligned pairs, the surface over every placement (built on
:mod:`enmi_torch.placement`), the loss and the class; a new option of a family is added in its file only.

The package re-exports the objects and each family's functions (value, ``_surface`` and ``_loss``): ``ecr``,
``enmi``, ``nmi`` and ``ncc`` here are the functions; import a family's module by its full name
(``from enmi_torch.scores.ecr import ...``) for the rest of it.
"""

from enmi_torch.scores.base import REDUCTIONS, Score, as_score, direct_surface, score_names
from enmi_torch.scores.ecr import ECR, ecr, ecr_loss, ecr_surface
from enmi_torch.scores.enmi import ENMI, enmi, enmi_loss, enmi_surface
from enmi_torch.scores.mixture import Mixture, mixture_information, mixture_loss, mixture_surface
from enmi_torch.scores.ncc import NCC, ncc, ncc_loss, ncc_surface
from enmi_torch.scores.nmi import NMI, nmi, nmi_loss, nmi_surface

__all__ = [
    "ECR",
    "ENMI",
    "NCC",
    "NMI",
    "REDUCTIONS",
    "Mixture",
    "Score",
    "as_score",
    "direct_surface",
    "ecr",
    "ecr_loss",
    "ecr_surface",
    "enmi",
    "enmi_loss",
    "enmi_surface",
    "mixture_information",
    "mixture_loss",
    "mixture_surface",
    "ncc",
    "ncc_loss",
    "ncc_surface",
    "nmi",
    "nmi_loss",
    "nmi_surface",
    "score_names",
]
