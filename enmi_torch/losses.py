"""Loss modules: a :class:`~enmi_torch.scores.Score`'s loss with its reduction and an optional variance model.

:class:`ScoreLoss` takes any score (``2 - NMI``, ``2 - ENMI``, ``1 - NCC``: 0 when aligned; ``-ECR``, ``-M``: lower
as the reference explains more); :class:`ECRLoss`, :class:`ENMILoss`, :class:`NMILoss` and :class:`MixtureLoss` build
their family's score from keyword options (or take one). The score owns its options and their defaults: for any
options, ``NMILoss(**options)(c, r)``, ``ScoreLoss(NMI(**options))(c, r)``, ``NMI(**options).loss(c, r)`` and the
functional ``nmi_loss(c, r, **options)`` (:mod:`enmi_torch.functional`) are one computation, with one value and one
gradient. A score that carries no gradient (``NMI(kernel="hard")``, see
:attr:`~enmi_torch.scores.Score.is_differentiable`) is refused with a ``ValueError`` naming the option to change.
"""

from __future__ import annotations

from typing import Any, ClassVar

from torch import Tensor, nn

from enmi_torch.scores import ECR, ENMI, NMI, REDUCTIONS, Mixture, Score, as_score
from enmi_torch.utils.checks import check_option
from enmi_torch.variance.base import VarianceModel, call_variance, check_variance_model

__all__ = ["ECRLoss", "ENMILoss", "MixtureLoss", "NMILoss", "ScoreLoss"]


class ScoreLoss(nn.Module):
    """A score's loss as a module: the score, the reduction and an optional variance model stored.

    The variance comes per call (``forward(captured, reference, variance)``) or from a
    :class:`~enmi_torch.variance.VarianceModel` given at construction (an analytic camera map, a learned mask): one or
    the other, not both. The model's :meth:`~enmi_torch.variance.VarianceModel.valid_mask` is combined with the call's
    ``valid_mask``; its parameters are this module's parameters, so the variance can be learned through the loss.
    Tensor options of the score (ENMI's ``log_prior``) are non-persistent buffers: they follow ``.to()``.

    Args:
        score: a :class:`~enmi_torch.scores.Score` or its name; one that carries a gradient.
        variance_model: optional :class:`~enmi_torch.variance.VarianceModel`, for scores that use a variance.
        reduction: ``"none"`` (``(B,)``), ``"mean"`` or ``"sum"``.

    Raises:
        ValueError: for a score without gradient (``NMI(kernel="hard")``), naming the option to change.

    Example:
        >>> from enmi_torch import ENMI
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> loss = ScoreLoss(ENMI(bins=4))
        >>> loss(image, image, 1e-6), loss(image, image.mT, 1e-6)
        (tensor(0.), tensor(1.))
    """

    def __init__(
        self, score: Score | str, *, variance_model: VarianceModel | None = None, reduction: str = "mean"
    ) -> None:
        super().__init__()
        self.score = as_score(score)
        self.score.check_differentiable()
        self.reduction = check_option("reduction", reduction, REDUCTIONS)
        self.variance_model = check_variance_model(variance_model)
        if variance_model is not None and not self.score.uses_variance:
            raise ValueError(f"variance_model is only used by scores that use a variance, got score {self.score!r}")
        for name, value in self.score.options.items():
            if isinstance(value, Tensor):
                self.register_buffer(name, value, persistent=False)

    def _apply(self, fn, recurse: bool = True):
        # .to(), .double(), .cuda() convert the buffers: the score takes the converted tensors.
        super()._apply(fn, recurse)
        tensors = {name: buffer for name, buffer in self.named_buffers(recurse=False) if name in self.score.options}
        if tensors:
            self.score = self.score.replace(**tensors)
        return self

    def forward(
        self,
        captured: Tensor,
        reference: Tensor,
        variance: Tensor | float | None = None,
        *,
        valid_mask: Tensor | None = None,
    ) -> Tensor:
        """Loss for ``captured`` and ``reference`` ``(B, 1, H, W)`` (or ``(B, H, W)``, flat samples ``(B, 1, N)``).

        ``variance`` as in the score, unless the module has a ``variance_model``.
        """
        variance, valid_mask = self._variance_and_mask(captured, variance, valid_mask)
        return self.score.loss(captured, reference, variance, valid_mask=valid_mask, reduction=self.reduction)

    def _variance_and_mask(self, captured: Tensor, variance, valid_mask):
        """The call's variance or the module's model's, and the call's mask combined with the model's."""
        name = type(self).__name__
        if self.variance_model is None:
            if variance is None and self.score.uses_variance:
                raise ValueError(f"variance must be given per call when {name} has no variance_model, got None")
            return variance, valid_mask
        call_variance(name, variance, self.variance_model)
        model_mask = self.variance_model.valid_mask(captured)
        if model_mask is not None:
            valid_mask = model_mask if valid_mask is None else valid_mask & model_mask
        return self.variance_model(captured), valid_mask


class _FamilyLoss(ScoreLoss):
    """A :class:`ScoreLoss` of one family, built from the family's options or given its score."""

    family: ClassVar[type[Score]]

    def __init__(
        self,
        score: Score | None = None,
        *,
        variance_model: VarianceModel | None = None,
        reduction: str = "mean",
        **options: Any,
    ) -> None:
        name = type(self).__name__
        if score is None:
            score = self.family(**options)
        elif options:
            raise TypeError(f"{name} takes a score or its options, not both; got {score!r} and {sorted(options)}")
        elif not isinstance(score, self.family):
            raise TypeError(f"{name} needs a score of the family {self.family.__name__}, got {score!r}")
        super().__init__(score, variance_model=variance_model, reduction=reduction)


class NMILoss(_FamilyLoss):
    """``2 - NMI(captured, reference)``, in ``[0, 1]``: :class:`ScoreLoss` of :class:`~enmi_torch.NMI`.

    Args:
        score: an :class:`~enmi_torch.NMI`, or ``None`` to build one from ``options``.
        variance_model: not used by NMI (``None``).
        reduction: ``"none"`` (``(B,)``), ``"mean"`` or ``"sum"``.
        **options: :class:`~enmi_torch.NMI`'s options, with its defaults (``kernel="triangular"``: a gradient;
            ``kernel="hard"``, without one, is refused).

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> NMILoss(bins=4)(image, image), NMILoss(bins=4)(image, image.mT)
        (tensor(0.5727), tensor(0.9927))
    """

    family = NMI


class ENMILoss(_FamilyLoss):
    """``2 - ENMI(captured, reference, variance)``, in ``[0, 1]``: :class:`ScoreLoss` of :class:`~enmi_torch.ENMI`.

    Args:
        score: an :class:`~enmi_torch.ENMI`, or ``None`` to build one from ``options``.
        variance_model: optional :class:`~enmi_torch.variance.VarianceModel` (see :class:`ScoreLoss`).
        reduction: ``"none"`` (``(B,)``), ``"mean"`` or ``"sum"``.
        **options: :class:`~enmi_torch.ENMI`'s options (``bins``, ``kernel``, ``log_prior``, ...).

    Example:
        >>> from enmi_torch.variance import ConstantVariance
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> loss = ENMILoss(bins=4, variance_model=ConstantVariance(1e-6))
        >>> loss(image, image)
        tensor(0.)
    """

    family = ENMI


class ECRLoss(_FamilyLoss):
    """``-ECR(captured, reference, variance)`` (nats per pixel): :class:`ScoreLoss` of :class:`~enmi_torch.ECR`.

    Args:
        score: an :class:`~enmi_torch.ECR`, or ``None`` to build one from ``options``.
        variance_model: optional :class:`~enmi_torch.variance.VarianceModel` (see :class:`ScoreLoss`).
        reduction: ``"none"`` (``(B,)``), ``"mean"`` or ``"sum"``.
        **options: :class:`~enmi_torch.ECR`'s options (``bins``, ``model_variance``, ``response``, ...).

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> loss = ECRLoss(bins=4)
        >>> loss(image, image, 1.0), loss(image, image.transpose(-1, -2), variance=1.0)
        (tensor(-5.9688), tensor(0.0078))
    """

    family = ECR


class MixtureLoss(_FamilyLoss):
    """``-M(captured, reference, variance)`` (nats per pixel): :class:`ScoreLoss` of :class:`~enmi_torch.Mixture`.

    Args:
        score: a :class:`~enmi_torch.Mixture`, or ``None`` to build one from ``options``.
        variance_model: optional :class:`~enmi_torch.variance.VarianceModel` (see :class:`ScoreLoss`).
        reduction: ``"none"`` (``(B,)``), ``"mean"`` or ``"sum"``.
        **options: :class:`~enmi_torch.Mixture`'s options (``bins``, ``value_range``, ``em_steps``).

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> loss = MixtureLoss(bins=4)
        >>> round(loss(image, image, variance=1.0).item(), 4), round(loss(image, image.mT, variance=1.0).item(), 4)
        (-1.3863, 0.0)
    """

    family = Mixture
