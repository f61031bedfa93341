"""The variance interface: a module that gives the per-pixel noise variance of a captured image."""

from __future__ import annotations

import abc

import torch
from torch import Tensor, nn

from enmi_torch.utils.checks import check_floating, check_positive_number


class VarianceModel(nn.Module, abc.ABC):
    """Interface of the variance maps that :class:`~enmi_torch.losses.ENMILoss` can own.

    A variance model maps a captured batch ``(B, 1, H, W)`` to its per-pixel noise variance, ``(1, 1, H, W)``
    (the same for every sample, e.g. an analytic camera map or a learned mask) or ``(B, 1, H, W)``, > 0 where
    valid. Models that know where they are invalid (out of view, out of sensor range) say so in
    :meth:`valid_mask`; :class:`~enmi_torch.losses.ENMILoss` then leaves those pixels out.
    """

    @abc.abstractmethod
    def forward(self, captured: Tensor) -> Tensor:
        """Variance ``(1 or B, 1, H, W)`` for the captured batch ``(B, 1, H, W)``."""

    def valid_mask(self, captured: Tensor) -> Tensor | None:
        """Bool ``(1 or B, 1, H, W)`` of the pixels where the variance is defined, or ``None`` for all."""
        return None


def check_variance_model(variance_model: object) -> VarianceModel | None:
    """``variance_model`` itself when it is ``None`` or a :class:`VarianceModel`; ``TypeError`` otherwise."""
    if variance_model is not None and not isinstance(variance_model, VarianceModel):
        raise TypeError(
            f"variance_model must be an enmi_torch.variance.VarianceModel, got {type(variance_model).__name__}"
        )
    return variance_model


def call_variance(owner: str, variance: object, variance_model: VarianceModel | None) -> object:
    """The variance of a module's call: the call's own, or the stored ``variance_model`` (never both)."""
    if variance_model is None:
        return variance
    if variance is not None:
        raise ValueError(f"variance must be None when {owner} has a variance_model; pass one or the other")
    return variance_model


class ConstantVariance(VarianceModel):
    """The same noise variance at every pixel: ENMI's baseline, which ignores where the noise comes from.

    Args:
        variance: the variance, > 0.
        learnable: fit ``log(variance)`` as a parameter.

    Example:
        >>> model = ConstantVariance(4.0)
        >>> model(torch.zeros(2, 1, 3, 3)).shape
        torch.Size([1, 1, 3, 3])
    """

    def __init__(self, variance: float = 1.0, *, learnable: bool = False) -> None:
        super().__init__()
        log_variance = torch.tensor(check_positive_number("variance", variance)).log()
        if learnable:
            self.log_variance = nn.Parameter(log_variance)
        else:
            self.register_buffer("log_variance", log_variance)

    def forward(self, captured: Tensor) -> Tensor:
        """The constant variance as ``(1, 1, H, W)`` for a captured batch ``(B, 1, H, W)``."""
        check_floating("captured", captured)
        if captured.ndim != 4:
            raise ValueError(f"captured must have shape (B, 1, H, W), got {tuple(captured.shape)}")
        variance = self.log_variance.exp().to(captured.dtype)
        return variance.expand(1, 1, *captured.shape[-2:])
