"""Undo a global intensity change between a captured image and its reference before taking residuals."""

from __future__ import annotations

import torch
from torch import Tensor

from enmi_torch.utils.checks import check_bool_mask, check_floating, check_not_empty


def match_intensity(captured: Tensor, reference: Tensor, valid_mask: Tensor | None = None) -> Tensor:
    """The reference mapped by the per-pair affine ``g * reference + o`` closest to ``captured`` in least squares.

    Lighting, sensor gain or map processing can change intensities between a captured (local) image and the prior map;
    a variance mask fitted to raw residuals would absorb that change. Fitting ``captured ~ g reference + o`` per pair
    on the valid pixels and taking residuals against the fitted reference removes it (two fitted numbers per pair of
    ``H * W`` pixels, so the residual variance is not noticeably reduced).

    Args:
        captured: ``(B, 1, H, W)`` or ``(B, H, W)``, floating point (masked pixels may hold NaN).
        reference: the matching prior-map sections, same shape.
        valid_mask: bool, same shape, or ``None`` for all pixels; a pair needs two valid pixels with different
            reference values, or its reference is shifted by the mean difference only (``g = 1``).

    Returns:
        The fitted reference, shape and dtype of ``reference``. No gradient through ``g`` and ``o``.

    Example:
        >>> reference = torch.tensor([[0.0, 1.0, 2.0, 3.0]])
        >>> match_intensity(2 * reference + 5, reference)
        tensor([[ 5.,  7.,  9., 11.]])
    """
    check_floating("captured", captured)
    check_floating("reference", reference)
    if captured.shape != reference.shape or captured.ndim < 2:
        raise ValueError(
            f"reference must have the shape of captured {tuple(captured.shape)}, got {tuple(reference.shape)}"
        )
    check_not_empty("captured", captured)
    if valid_mask is None:
        valid_mask = torch.ones_like(reference, dtype=torch.bool)
    check_bool_mask("valid_mask", valid_mask)
    if valid_mask.shape != reference.shape:
        raise ValueError(
            f"valid_mask must be a bool tensor of shape {tuple(reference.shape)}, got {valid_mask.dtype} "
            f"{tuple(valid_mask.shape)}"
        )
    with torch.no_grad():
        weight = valid_mask.reshape(reference.shape[0], -1).to(torch.float64)
        x = torch.where(valid_mask, reference, 0.0).reshape(reference.shape[0], -1).to(torch.float64)
        y = torch.where(valid_mask, captured, 0.0).reshape(reference.shape[0], -1).to(torch.float64)
        count = weight.sum(dim=1).clamp_min(1)
        x_mean, y_mean = x.sum(dim=1) / count, y.sum(dim=1) / count
        x_centred = (x - x_mean.unsqueeze(1)) * weight
        spread = x_centred.square().sum(dim=1)
        gain = torch.where(
            spread > 0, (x_centred * (y - y_mean.unsqueeze(1))).sum(dim=1) / spread.clamp_min(1e-300), 1.0
        )
        offset = y_mean - gain * x_mean
    shape = (-1,) + (1,) * (reference.ndim - 1)
    return reference * gain.to(reference.dtype).reshape(shape) + offset.to(reference.dtype).reshape(shape)
