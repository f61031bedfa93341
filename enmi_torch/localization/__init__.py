"""Localization: the pose of one frame in a map from score surfaces, its sub-cell peak.

Data flow, each module importing only the ones before it: the score surfaces (:mod:`enmi_torch.scores`, every
placement at once by FFT) → :mod:`~enmi_torch.localization.peak` (the :class:`Localization` result: sub-cell peak,
covariance, margin) → :mod:`~enmi_torch.localization.strategy` (:class:`SearchStrategy`: how the candidates are
visited) → :mod:`~enmi_torch.localization.candidates` (windows, rotations, surfaces) →
:mod:`~enmi_torch.localization.search` (shifts x yaws: :func:`localize`, :class:`Localizer`). The command line
(``enmi-localize``) is :mod:`enmi_torch.cli.localize`; a drive (the histogram filter :class:`~enmi_torch.Tracker`)
builds on :func:`localize` in :mod:`enmi_torch.tracking`.
"""

from enmi_torch.localization.peak import Finalists, Localization, NoCandidateError
from enmi_torch.localization.search import Localizer, localize
from enmi_torch.localization.strategy import SearchStrategy

__all__ = ["Finalists", "Localization", "Localizer", "NoCandidateError", "SearchStrategy", "localize"]
