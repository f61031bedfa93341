"""Losses: ``2 - NMI``, ``2 - ENMI`` (0 when aligned), ``-ECR``, ``-M`` (lower as the reference explains more).

Each loss is a function (``nmi_loss``, ``enmi_loss``, ``ecr_loss``, ``mixture_loss``: every setting per call) and a
module (``NMILoss``, ...: settings and an optional variance model stored, ``forward(captured, reference, *,
variance=None, valid_mask=None)``), as in kornia. The losses default to a differentiable captured kernel
(``"triangular"`` for NMI); :func:`~enmi_torch.information.nmi`, a measurement, defaults to hard bins (scikit-image's
NMI).
"""

from __future__ import annotations

from torch import Tensor, nn

from enmi_torch._checks import check_bins, check_non_negative_int, check_option, check_value_range
from enmi_torch.binning import LIKELIHOOD_WEIGHTS, PARZEN_KERNELS
from enmi_torch.correlation_ratio import RESPONSES, check_model_variance, ecr
from enmi_torch.information import enmi, nmi
from enmi_torch.mixture import mixture_information
from enmi_torch.variance.base import VarianceModel, check_variance_model

REDUCTIONS = ("none", "mean", "sum")


def _store_histogram_options(module: nn.Module, bins, value_range, reference_kernel, reduction) -> None:
    """Check and store the hyper-parameters both losses share."""
    module.bins = check_bins(bins)
    module.value_range = check_value_range(value_range)
    module.reference_kernel = check_option("reference_kernel", reference_kernel, PARZEN_KERNELS)
    module.reduction = check_option("reduction", reduction, REDUCTIONS)


def _reduce(loss: Tensor, reduction: str) -> Tensor:
    if reduction == "mean":
        return loss.mean()
    if reduction == "sum":
        return loss.sum()
    return loss


def nmi_loss(
    captured: Tensor,
    reference: Tensor,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    kernel: str = "triangular",
    reference_kernel: str = "hard",
    valid_mask: Tensor | None = None,
    reduction: str = "mean",
) -> Tensor:
    """``2 - nmi(captured, reference)`` reduced over the batch; arguments as :func:`~enmi_torch.information.nmi`.

    The default ``kernel`` is ``"triangular"`` (a gradient); ``"hard"`` gives the measurement, without gradient.

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> nmi_loss(image, image, bins=4, kernel="hard"), nmi_loss(image, image.mT, bins=4, kernel="hard")
        (tensor(0.), tensor(1.))
    """
    check_option("reduction", reduction, REDUCTIONS)
    score = nmi(
        captured,
        reference,
        bins=bins,
        value_range=value_range,
        kernel=kernel,
        reference_kernel=reference_kernel,
        valid_mask=valid_mask,
    )
    return _reduce(2 - score, reduction)


def enmi_loss(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    kernel: str = "mass",
    log_prior: Tensor | None = None,
    reference_kernel: str = "hard",
    valid_mask: Tensor | None = None,
    reliability: bool = False,
    reduction: str = "mean",
) -> Tensor:
    """``2 - enmi(captured, reference, variance)`` reduced; arguments as :func:`~enmi_torch.information.enmi`.

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> enmi_loss(image, image, 1e-6, bins=4), enmi_loss(image, image.mT, 1e-6, bins=4)
        (tensor(0.), tensor(1.))
    """
    check_option("reduction", reduction, REDUCTIONS)
    score = enmi(
        captured,
        reference,
        variance,
        bins=bins,
        value_range=value_range,
        kernel=kernel,
        log_prior=log_prior,
        reference_kernel=reference_kernel,
        valid_mask=valid_mask,
        reliability=reliability,
    )
    return _reduce(2 - score, reduction)


def ecr_loss(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    model_variance: float | None = None,
    valid_mask: Tensor | None = None,
    response: str = "binned",
    reduction: str = "mean",
) -> Tensor:
    """``-ecr(captured, reference, variance)`` reduced; arguments as :func:`~enmi_torch.correlation_ratio.ecr`.

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> ecr_loss(image, image, 1.0, bins=4), ecr_loss(image, image.mT, 1.0, bins=4)
        (tensor(-7.3843), tensor(-0.3736))
    """
    check_option("reduction", reduction, REDUCTIONS)
    score = ecr(
        captured,
        reference,
        variance,
        bins=bins,
        value_range=value_range,
        model_variance=model_variance,
        valid_mask=valid_mask,
        response=response,
    )
    return _reduce(-score, reduction)


def mixture_loss(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    em_steps: int = 0,
    valid_mask: Tensor | None = None,
    reduction: str = "mean",
) -> Tensor:
    """``-mixture_information(captured, reference, variance)`` reduced; see :func:`~enmi_torch.mixture_information`.

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> round(mixture_loss(image, image, 1.0, bins=4).item(), 4)
        -1.3863
    """
    check_option("reduction", reduction, REDUCTIONS)
    score = mixture_information(
        captured, reference, variance, bins=bins, value_range=value_range, em_steps=em_steps, valid_mask=valid_mask
    )
    return _reduce(-score, reduction)


class NMILoss(nn.Module):
    """``2 - NMI(captured, reference)``, in ``[0, 1]``; the module form of :func:`~enmi_torch.information.nmi`.

    Args:
        bins: number of bins.
        value_range: ``(low, high)`` of the bins.
        kernel: ``"triangular"`` (default) or ``"xu"`` for a gradient; ``"hard"`` for evaluation only.
        reference_kernel: ``"hard"`` (default), ``"triangular"`` or ``"xu"``.
        reduction: ``"none"`` (``(B,)``), ``"mean"`` or ``"sum"``.

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> NMILoss(bins=4, kernel="hard")(image, image)
        tensor(0.)
    """

    def __init__(
        self,
        bins: int = 32,
        value_range: tuple[float, float] = (0.0, 256.0),
        kernel: str = "triangular",
        reference_kernel: str = "hard",
        reduction: str = "mean",
    ) -> None:
        super().__init__()
        _store_histogram_options(self, bins, value_range, reference_kernel, reduction)
        self.kernel = check_option("kernel", kernel, PARZEN_KERNELS)

    def forward(self, captured: Tensor, reference: Tensor, *, valid_mask: Tensor | None = None) -> Tensor:
        """Loss for ``captured`` and ``reference`` ``(B, 1, H, W)`` (or ``(B, H, W)``, ``(B, N)``)."""
        return nmi_loss(
            captured,
            reference,
            bins=self.bins,
            value_range=self.value_range,
            kernel=self.kernel,
            reference_kernel=self.reference_kernel,
            valid_mask=valid_mask,
            reduction=self.reduction,
        )


class ENMILoss(nn.Module):
    """``2 - ENMI(captured, reference, variance)``, in ``[0, 1]``; module form of :func:`~enmi_torch.information.enmi`.

    The variance comes per call (``forward(..., variance=...)``) or from a :class:`~enmi_torch.variance.VarianceModel`
    given at construction (an analytic camera map, a learned mask): one or the other, not both. The model's
    :meth:`~enmi_torch.variance.VarianceModel.valid_mask` is combined with the call's ``valid_mask``; its parameters
    are this module's parameters, so the variance can be learned through the loss.

    Args:
        bins: number of bins.
        value_range: ``(low, high)`` of the bins.
        kernel: ``"mass"``, ``"density"`` or ``"truncated"`` (see :func:`~enmi_torch.information.enmi`).
        log_prior: optional ``(bins,)`` log prior of the amplitudes (a non-persistent buffer).
        variance_model: optional :class:`~enmi_torch.variance.VarianceModel`.
        reference_kernel: ``"hard"`` (default), ``"triangular"`` or ``"xu"``.
        reduction: ``"none"`` (``(B,)``), ``"mean"`` or ``"sum"``.
        reliability: reliability-weighted counts (see :func:`~enmi_torch.information.enmi`).

    Example:
        >>> from enmi_torch.variance import ConstantVariance
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> loss = ENMILoss(bins=4, variance_model=ConstantVariance(1e-6))
        >>> loss(image, image)
        tensor(0.)
    """

    def __init__(
        self,
        bins: int = 32,
        value_range: tuple[float, float] = (0.0, 256.0),
        kernel: str = "mass",
        log_prior: Tensor | None = None,
        variance_model: VarianceModel | None = None,
        reference_kernel: str = "hard",
        reduction: str = "mean",
        reliability: bool = False,
    ) -> None:
        super().__init__()
        _store_histogram_options(self, bins, value_range, reference_kernel, reduction)
        self.kernel = check_option("kernel", kernel, LIKELIHOOD_WEIGHTS)
        if not isinstance(reliability, bool):
            raise TypeError(f"reliability must be True or False, got {reliability!r}")
        self.reliability = reliability
        self.variance_model = check_variance_model(variance_model)
        self.register_buffer("log_prior", log_prior, persistent=False)

    def forward(
        self,
        captured: Tensor,
        reference: Tensor,
        *,
        variance: Tensor | float | None = None,
        valid_mask: Tensor | None = None,
    ) -> Tensor:
        """Loss for ``captured`` and ``reference`` ``(B, 1, H, W)``; ``variance`` as in :func:`enmi`."""
        variance, valid_mask = _variance_and_mask(self, "ENMILoss", captured, variance, valid_mask)
        return enmi_loss(
            captured,
            reference,
            variance,
            bins=self.bins,
            value_range=self.value_range,
            kernel=self.kernel,
            log_prior=self.log_prior,
            reference_kernel=self.reference_kernel,
            valid_mask=valid_mask,
            reliability=self.reliability,
            reduction=self.reduction,
        )


class ECRLoss(nn.Module):
    """``-ECR(captured, reference, variance)`` (nats per pixel): the module form of :func:`~enmi_torch.ecr`.

    The variance comes per call or from a :class:`~enmi_torch.variance.VarianceModel` given at construction, as in
    :class:`ENMILoss`; the model's parameters get gradients through the loss.

    Args:
        bins: number of reference bins.
        value_range: ``(low, high)`` of the reference bins.
        model_variance: ``tau^2 >= 0``; ``None`` for ``bin_width^2 / 12``.
        variance_model: optional :class:`~enmi_torch.variance.VarianceModel`.
        reduction: ``"none"`` (``(B,)``), ``"mean"`` or ``"sum"``.
        response: ``"binned"`` (any response) or ``"linear"`` (see :func:`~enmi_torch.ecr`).

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> loss = ECRLoss(bins=4)
        >>> loss(image, image, variance=1.0), loss(image, image.transpose(-1, -2), variance=1.0)
        (tensor(-7.3843), tensor(-0.3736))
    """

    def __init__(
        self,
        bins: int = 32,
        value_range: tuple[float, float] = (0.0, 256.0),
        model_variance: float | None = None,
        variance_model: VarianceModel | None = None,
        reduction: str = "mean",
        response: str = "binned",
    ) -> None:
        super().__init__()
        self.bins = check_bins(bins)
        self.value_range = check_value_range(value_range)
        self.model_variance = check_model_variance(model_variance, self.bins, self.value_range)
        self.response = check_option("response", response, RESPONSES)
        self.reduction = check_option("reduction", reduction, REDUCTIONS)
        self.variance_model = check_variance_model(variance_model)

    def forward(
        self,
        captured: Tensor,
        reference: Tensor,
        *,
        variance: Tensor | float | None = None,
        valid_mask: Tensor | None = None,
    ) -> Tensor:
        """Loss for ``captured`` and ``reference`` ``(B, 1, H, W)``; ``variance`` as in :func:`ecr`."""
        variance, valid_mask = _variance_and_mask(self, "ECRLoss", captured, variance, valid_mask)
        return ecr_loss(
            captured,
            reference,
            variance,
            bins=self.bins,
            value_range=self.value_range,
            model_variance=self.model_variance,
            valid_mask=valid_mask,
            response=self.response,
            reduction=self.reduction,
        )


class MixtureLoss(nn.Module):
    """``-M(captured, reference, variance)`` (nats per pixel): module form of :func:`~enmi_torch.mixture_information`.

    The variance comes per call or from a :class:`~enmi_torch.variance.VarianceModel` given at construction, as in
    :class:`ENMILoss`.

    Args:
        bins: number of bins.
        value_range: ``(low, high)`` of the bins.
        em_steps: EM steps (see :func:`~enmi_torch.mixture_information`).
        variance_model: optional :class:`~enmi_torch.variance.VarianceModel`.
        reduction: ``"none"`` (``(B,)``), ``"mean"`` or ``"sum"``.

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> loss = MixtureLoss(bins=4)
        >>> round(loss(image, image, variance=1.0).item(), 4), round(loss(image, image.mT, variance=1.0).item(), 4)
        (-1.3863, 0.0)
    """

    def __init__(
        self,
        bins: int = 32,
        value_range: tuple[float, float] = (0.0, 256.0),
        em_steps: int = 0,
        variance_model: VarianceModel | None = None,
        reduction: str = "mean",
    ) -> None:
        super().__init__()
        self.bins = check_bins(bins)
        self.value_range = check_value_range(value_range)
        self.em_steps = check_non_negative_int("em_steps", em_steps)
        self.reduction = check_option("reduction", reduction, REDUCTIONS)
        self.variance_model = check_variance_model(variance_model)

    def forward(
        self,
        captured: Tensor,
        reference: Tensor,
        *,
        variance: Tensor | float | None = None,
        valid_mask: Tensor | None = None,
    ) -> Tensor:
        """Loss for ``captured`` and ``reference`` ``(B, 1, H, W)``; ``variance`` as in :func:`mixture_information`."""
        variance, valid_mask = _variance_and_mask(self, "MixtureLoss", captured, variance, valid_mask)
        return mixture_loss(
            captured,
            reference,
            variance,
            bins=self.bins,
            value_range=self.value_range,
            em_steps=self.em_steps,
            valid_mask=valid_mask,
            reduction=self.reduction,
        )


def _variance_and_mask(module: nn.Module, name: str, captured: Tensor, variance, valid_mask):
    """The call's variance or the module's model's, and the call's mask combined with the model's."""
    if variance is None and module.variance_model is None:
        raise ValueError(f"variance must be given per call when {name} has no variance_model, got None")
    if variance is not None and module.variance_model is not None:
        raise ValueError(f"variance must be None when {name} has a variance_model; pass one or the other")
    if module.variance_model is not None:
        variance = module.variance_model(captured)
        model_mask = module.variance_model.valid_mask(captured)
        if model_mask is not None:
            valid_mask = model_mask if valid_mask is None else valid_mask & model_mask
    return variance, valid_mask
