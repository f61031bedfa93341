"""The paper's empirical variance mask from matching local/prior image pairs, streaming over batches and processes.

The paper (section "Ford Image Analysis") estimates the noise variance of pixel ``[i, j]`` from ``n`` matching
local images ``a`` and prior-map sections ``a~`` as ``Var[i, j] = 1 / (n - 1) sum_k (a_ij^(k) - a~_ij^(k))^2``.
Its state is two sums per pixel (the number of valid observations and the sum of squared residuals), so batches,
chunks of a dataset larger than memory and the processes of a distributed run each add their own sums and the
result is the same as one pass over all pairs.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from enmi_torch.utils.checks import (
    check_finite_where,
    check_floating,
    check_image_shape,
    check_no_overflow,
    check_non_negative_int,
    check_not_empty,
)
from enmi_torch.utils.layout import mask_map, spatial_shape


def empirical_variance(
    captured: Tensor, reference: Tensor, valid_mask: Tensor | None = None, *, ddof: int = 1
) -> tuple[Tensor, Tensor]:
    """The paper's per-pixel variance ``1 / (n - ddof) sum_k (local_k - prior_k)^2`` over a batch of pairs.

    Args:
        captured: captured (local) images ``(B, 1, H, W)`` or ``(B, H, W)``, floating point.
        reference: the matching prior-map sections, same shape.
        valid_mask: bool, ``(H, W)``, ``(1, 1, H, W)`` or one map per pair (``(B, 1, H, W)``, ``(B, H, W)``);
            ``False`` pixels of a pair are left out of that pixel's sum and count (they may hold NaN).
        ddof: ``n - ddof`` divides the sum; 1 (default) is the paper's estimator, 0 the maximum-likelihood one.

    Returns:
        ``(variance, valid)``, both ``(H, W)``: the variance in float64, NaN where it is undefined, and the bool map
        of the pixels with more than ``ddof`` valid observations (where it is defined).

    Convention:
        Residuals are not centred: the pairs are assumed to match, so the mean residual is 0 (as in the paper).
        Sums are accumulated in float64 whatever the input dtype. No gradient.

    Example:
        >>> captured = torch.tensor([[[1.0, 2.0]], [[3.0, 2.0]]])
        >>> reference = torch.zeros(2, 1, 2)
        >>> variance, valid = empirical_variance(captured, reference)
        >>> variance
        tensor([[10.,  8.]], dtype=torch.float64)
        >>> empirical_variance(captured, reference, torch.tensor([[[True, True]], [[False, True]]]))[1]
        tensor([[False,  True]])
    """
    count, sum_squares = _accumulate(captured, reference, valid_mask)
    return _compute(count, sum_squares, check_non_negative_int("ddof", ddof))


def _accumulate(captured: Tensor, reference: Tensor, valid_mask: Tensor | None) -> tuple[Tensor, Tensor]:
    """Per-pixel number of valid pairs (int64) and sum of squared residuals (float64), both ``(H, W)``."""
    check_floating("captured", captured)
    check_floating("reference", reference)
    if captured.ndim not in (3, 4):
        raise ValueError(f"captured must have shape (B, 1, H, W) or (B, H, W), got {tuple(captured.shape)}")
    if reference.shape != captured.shape:
        raise ValueError(
            f"reference must have the shape of captured {tuple(captured.shape)}, got {tuple(reference.shape)}"
        )
    shape = spatial_shape("captured", captured)
    check_not_empty("captured", captured)
    residual = (captured.to(torch.float64) - reference.to(torch.float64)).reshape(captured.shape[0], -1)
    if valid_mask is None:
        valid = torch.ones_like(residual, dtype=torch.bool)
    else:
        valid = mask_map("valid_mask", valid_mask, captured, "captured", require_pixels=False)
    check_finite_where("captured - reference", residual, valid)
    sum_squares = torch.where(valid, residual, 0.0).square().sum(dim=0)
    check_no_overflow(
        "the sum of squared residuals",
        sum_squares,
        "captured - reference holds residuals too large to square (beyond ~1.3e154); rescale both images",
    )
    return valid.sum(dim=0).reshape(shape), sum_squares.reshape(shape)


def _compute(count: Tensor, sum_squares: Tensor, ddof: int) -> tuple[Tensor, Tensor]:
    valid = count > ddof
    variance = torch.where(valid, sum_squares / (count - ddof).clamp_min(1), torch.nan)
    return variance, valid


class EmpiricalVariance(nn.Module):
    """Streaming form of :func:`empirical_variance`: sums that add across batches, datasets and processes.

    The state (``count``, ``sum_squares``, ``(H, W)``) is held in persistent buffers, so it travels in checkpoints
    and follows :meth:`~torch.nn.Module.to`. :meth:`update` adds a batch, :meth:`merge` adds another accumulator's
    sums, :meth:`all_reduce` sums the state over the processes of a ``torch.distributed`` group, :meth:`compute`
    returns the mask.

    Args:
        shape: ``(H, W)`` of the images.
        ddof: as in :func:`empirical_variance`; 1 is the paper's estimator.

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> captured, reference = torch.randn(6, 1, 4, 4, generator=generator), torch.zeros(6, 1, 4, 4)
        >>> stream = EmpiricalVariance((4, 4))
        >>> for start in range(0, 6, 2):
        ...     stream.update(captured[start : start + 2], reference[start : start + 2])
        >>> torch.allclose(stream.compute()[0], empirical_variance(captured, reference)[0])
        True
    """

    def __init__(self, shape: tuple[int, int], *, ddof: int = 1) -> None:
        super().__init__()
        self.shape = check_image_shape("shape", shape)
        self.ddof = check_non_negative_int("ddof", ddof)
        self.register_buffer("count", torch.zeros(self.shape, dtype=torch.int64))
        self.register_buffer("sum_squares", torch.zeros(self.shape, dtype=torch.float64))

    def update(self, captured: Tensor, reference: Tensor, valid_mask: Tensor | None = None) -> None:
        """Add a batch of pairs (shapes as in :func:`empirical_variance`, images ``(H, W)``)."""
        count, sum_squares = _accumulate(captured, reference, valid_mask)
        if tuple(count.shape) != self.shape:
            raise ValueError(f"captured must have images of shape {self.shape}, got {tuple(captured.shape)}")
        self.count += count.to(self.count.device)
        self.sum_squares += sum_squares.to(self.sum_squares.device)

    def merge(self, other: EmpiricalVariance) -> EmpiricalVariance:
        """Add the sums of ``other`` (same shape and ``ddof``) to this accumulator; returns ``self``."""
        if not isinstance(other, EmpiricalVariance):
            raise TypeError(f"other must be an EmpiricalVariance, got {type(other).__name__}")
        if other.shape != self.shape or other.ddof != self.ddof:
            raise ValueError(
                f"other must have shape {self.shape} and ddof {self.ddof}, "
                f"got shape {other.shape} and ddof {other.ddof}"
            )
        self.count += other.count.to(self.count.device)
        self.sum_squares += other.sum_squares.to(self.sum_squares.device)
        return self

    def all_reduce(self, group=None) -> None:
        """Sum the state over the processes of ``group`` (no-op without an initialised ``torch.distributed``)."""
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            torch.distributed.all_reduce(self.count, group=group)
            torch.distributed.all_reduce(self.sum_squares, group=group)

    def reset(self) -> None:
        """Forget every pair added so far."""
        self.count.zero_()
        self.sum_squares.zero_()

    def compute(self) -> tuple[Tensor, Tensor]:
        """``(variance, valid)``, both ``(H, W)``: float64 variance (NaN where undefined) and its bool valid map."""
        return _compute(self.count, self.sum_squares, self.ddof)

    def forward(self, captured: Tensor, reference: Tensor, valid_mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """Add a batch, then return :meth:`compute`."""
        self.update(captured, reference, valid_mask)
        return self.compute()

    def extra_repr(self) -> str:
        """Shape and ``ddof`` in the module's repr."""
        return f"shape={self.shape}, ddof={self.ddof}"
