"""Undo a global intensity change between a local image and its prior before taking residuals."""

from __future__ import annotations

import torch
from torch import Tensor

from enmi_torch._checks import check_floating, check_not_empty, check_tensor


def match_intensity(prior: Tensor, local: Tensor, valid_mask: Tensor | None = None) -> Tensor:
    """The prior mapped by the per-pair affine ``g * prior + o`` closest to ``local`` in least squares.

    Lighting, sensor gain or map processing can change intensities between a local capture and the prior map; a
    variance mask fitted to raw residuals would absorb that change. Fitting ``local ~ g prior + o`` per pair on the
    valid pixels and taking residuals against the fitted prior removes it (two fitted numbers per pair of
    ``H * W`` pixels, so the residual variance is not noticeably reduced).

    Args:
        prior: ``(B, 1, H, W)`` or ``(B, H, W)``, floating point.
        local: same shape.
        valid_mask: bool, same shape, or ``None`` for all pixels; a pair needs two valid pixels with different prior
            values, or its prior is shifted by the mean difference only (``g = 1``).

    Returns:
        The fitted prior, shape and dtype of ``prior``. No gradient through ``g`` and ``o``.

    Example:
        >>> prior = torch.tensor([[0.0, 1.0, 2.0, 3.0]])
        >>> match_intensity(prior, 2 * prior + 5)
        tensor([[ 5.,  7.,  9., 11.]])
    """
    check_floating("prior", prior)
    check_floating("local", local)
    if local.shape != prior.shape or prior.ndim < 2:
        raise ValueError(f"local must have the shape of prior {tuple(prior.shape)}, got {tuple(local.shape)}")
    check_not_empty("prior", prior)
    if valid_mask is None:
        valid_mask = torch.ones_like(prior, dtype=torch.bool)
    check_tensor("valid_mask", valid_mask)
    if valid_mask.dtype != torch.bool or valid_mask.shape != prior.shape:
        raise ValueError(
            f"valid_mask must be a bool tensor of shape {tuple(prior.shape)}, got {valid_mask.dtype} "
            f"{tuple(valid_mask.shape)}"
        )
    with torch.no_grad():
        weight = valid_mask.reshape(prior.shape[0], -1).to(torch.float64)
        x = torch.where(valid_mask, prior, 0.0).reshape(prior.shape[0], -1).to(torch.float64)
        y = torch.where(valid_mask, local, 0.0).reshape(prior.shape[0], -1).to(torch.float64)
        count = weight.sum(dim=1).clamp_min(1)
        x_mean, y_mean = x.sum(dim=1) / count, y.sum(dim=1) / count
        x_centred = (x - x_mean.unsqueeze(1)) * weight
        spread = x_centred.square().sum(dim=1)
        gain = torch.where(
            spread > 0, (x_centred * (y - y_mean.unsqueeze(1))).sum(dim=1) / spread.clamp_min(1e-300), 1.0
        )
        offset = y_mean - gain * x_mean
    shape = (-1,) + (1,) * (prior.ndim - 1)
    return prior * gain.to(prior.dtype).reshape(shape) + offset.to(prior.dtype).reshape(shape)
