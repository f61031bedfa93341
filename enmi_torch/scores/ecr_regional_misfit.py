"""ECR's regional misfit (``misfit="regional"``): a model variance ``tau^2(x)`` that varies over the captured image.

Model (:ref:`model-regional`): around each pixel, a precision-weighted local estimate of the misfit's variance from
the residuals ``r_n^2 - sigma_n^2`` over a box, shrunk toward the image's REML ``tau^2`` by empirical Bayes (as far as
its sampling variance outweighs the spread of the local variances), at least ``bin_width^2 / 12``.

One ``tau^2`` for the whole image lets the quiet pixels of a changed part of the scene (a new building, a shadow, a
parked car) keep the trust of their low sensor noise: their misfit is far larger than the image's average. The box
reaches :data:`REGIONAL_REACH` of the image's side on each axis; the response is refitted with the map's weights and
the map re-read :data:`REGIONAL_STEPS` times, the prior mean staying the REML ``tau^2``. A pixel's weight is then
``1 / (sigma_n^2 + tau^2(x_n))``; the map is held fixed in the gradient, and a surface holds the map read at its first
pass's peak at every placement, in the captured image's coordinates.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.nn import functional

# The box the local estimates average over reaches this fraction of the image's side on each axis.
REGIONAL_REACH = 1 / 8
# Rounds of the response refitted with the map's weights and the map re-read from its residuals.
REGIONAL_STEPS = 2


def regional_reach(height: int, width: int) -> tuple[int, int]:
    """The box half-sides ``(R_y, R_x)`` the regional misfit averages over: ``max(1, round(REGIONAL_REACH * side))``.

    Example:
        >>> regional_reach(48, 96)
        (6, 12)
    """
    return max(1, round(REGIONAL_REACH * height)), max(1, round(REGIONAL_REACH * width))


def _box_sums(values: Tensor, reach: tuple[int, int]) -> Tensor:
    """Sums of ``values`` ``(S, H, W)`` over the ``(2 R_y + 1) x (2 R_x + 1)`` box around each pixel, zero outside."""
    reach_y, reach_x = reach
    planes = values[:, None]
    along_rows = torch.ones(1, 1, 1, 2 * reach_x + 1, dtype=values.dtype, device=values.device)
    along_cols = torch.ones(1, 1, 2 * reach_y + 1, 1, dtype=values.dtype, device=values.device)
    planes = functional.conv2d(planes, along_rows, padding=(0, reach_x))
    return functional.conv2d(planes, along_cols, padding=(reach_y, 0))[:, 0]


def regional_model_variance(
    residual: Tensor,
    noise: Tensor,
    valid: Tensor,
    model_variance: Tensor,
    floor: float,
    weights_at: Tensor | None = None,
) -> Tensor:
    """The regional misfit's ``tau^2(x)`` ``(S, H, W)`` from the residuals of ``S`` aligned pairs (see the module).

    ``residual`` ``(S, H, W)``: the captured values less their fitted means; ``noise`` ``(S, H, W)``: ``sigma^2``;
    ``valid`` ``(S, H, W)`` bool; ``model_variance`` ``(S,)``: the image's REML ``tau^2``, the prior mean;
    ``floor``: the least ``tau^2(x)``; ``weights_at`` ``(S, H, W)``: the ``tau^2`` map whose weights ``u_n`` read
    the local estimates (``None``: ``model_variance`` everywhere). Invalid pixels may hold NaN; their ``tau^2(x)`` is
    read from the valid pixels around them (the image's ``tau^2`` without any). Same dtype as ``residual``.

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> residual = torch.randn(1, 32, 48, generator=generator, dtype=torch.float64)  # sigma^2 = 1, no misfit
        >>> residual[:, 8:16, 8:24] *= 10  # a changed patch: misfit about 99
        >>> noise, valid = torch.ones(1, 32, 48, dtype=torch.float64), torch.ones(1, 32, 48, dtype=torch.bool)
        >>> tau2 = regional_model_variance(residual, noise, valid, torch.tensor([8.0], dtype=torch.float64), 0.1)
        >>> bool(tau2[0, 12, 16] > 10 * tau2[0, 28, 40])
        True
    """
    _, height, width = residual.shape
    reach = regional_reach(height, width)
    prior = model_variance.to(residual.dtype)[:, None, None]
    around = prior if weights_at is None else weights_at
    mask = valid.to(residual.dtype)
    precision = mask / (torch.where(valid, noise, 1.0) + around).square()
    excess = torch.where(valid, residual.square() - noise, 0.0)  # an invalid pixel may hold NaN
    precision_sums = _box_sums(precision, reach)
    tiny = torch.finfo(residual.dtype).tiny
    seen = precision_sums > tiny
    local = torch.where(seen, _box_sums(precision * excess, reach) / precision_sums.clamp_min(tiny), prior)
    sampling = torch.where(seen, 2 / precision_sums.clamp_min(tiny), torch.inf)
    # The spread of the true local variances about the image's: moments over the valid pixels, at least 0.
    spread = torch.where(valid & seen, (local - prior).square() - sampling, 0.0).sum((1, 2))
    spread = (spread / (valid & seen).sum((1, 2)).clamp_min(1)).clamp_min(0)[:, None, None]
    share = torch.where(seen, spread / (spread + sampling).clamp_min(tiny), 0.0)
    return (prior + share * (local - prior)).clamp_min(floor)
