"""Scores of a captured image against a reference, one family per file, each an object and its functions.

:class:`~enmi_torch.scores.base.Score` (base class, :func:`~enmi_torch.scores.base.as_score`,
:func:`~enmi_torch.scores.base.direct_surface`) → the families :class:`ECR` (:mod:`~enmi_torch.scores.ecr`, with
:mod:`~enmi_torch.scores.ecr_statistics`, :mod:`~enmi_torch.scores.ecr_model_variance`,
:mod:`~enmi_torch.scores.ecr_placements` and :mod:`~enmi_torch.scores.shrunk_response`), :class:`ENMI`
(:mod:`~enmi_torch.scores.enmi`), :class:`NMI` (:mod:`~enmi_torch.scores.nmi`), :class:`NCC`
(:mod:`~enmi_torch.scores.ncc`) and :class:`Mixture` (:mod:`~enmi_torch.scores.mixture`, whose surface ranks
placements by ECR's). Each family's file owns the value on aligned pairs, the surface over every placement (built on
:mod:`enmi_torch.placement`), the loss and the class; a new option of a family is added in its file only.

The functions live in the family modules (``enmi_torch.scores.ecr.ecr``, ...; all of them in
:mod:`enmi_torch.functional`): the package re-exports the objects only, so that ``enmi_torch.scores.ecr`` stays the
module.
"""

from enmi_torch.scores.base import REDUCTIONS, Score, as_score, direct_surface, score_names
from enmi_torch.scores.ecr import ECR
from enmi_torch.scores.enmi import ENMI
from enmi_torch.scores.mixture import Mixture
from enmi_torch.scores.ncc import NCC
from enmi_torch.scores.nmi import NMI

__all__ = ["ECR", "ENMI", "NCC", "NMI", "REDUCTIONS", "Mixture", "Score", "as_score", "direct_surface", "score_names"]
