"""Image layouts: public functions accept ``(B, 1, H, W)`` or ``(B, H, W)`` and work on ``(B, N)``.

A 2-D tensor is refused: ``(64, 64)`` could be one ``(H, W)`` image (``captured[0, 0]``) or 64 flat samples of 64
pixels, and reading it either way would answer the other reading silently (64 per-row scores for one image). Flat
samples (tiles, point sets) are given as ``(B, 1, N)``, one row of ``N`` pixels per sample; one image as
``(1, 1, H, W)``.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from enmi_torch.utils.checks import (
    check_bool_mask,
    check_floating,
    check_mask_not_empty,
    check_not_empty,
    check_positive_where,
    check_real_data,
    check_tensor,
    check_variance_fits,
)


def spatial_shape(name: str, image: Tensor) -> tuple[int, ...]:
    """The per-sample shape of ``image`` without batch and channel: ``(H, W)``; a 2-D tensor is refused."""
    if image.ndim == 4:
        if image.shape[1] != 1:
            raise ValueError(f"{name} must have one channel, (B, 1, H, W), got shape {tuple(image.shape)}")
        return tuple(image.shape[2:])
    if image.ndim == 3:
        return tuple(image.shape[1:])
    if image.ndim == 2:
        raise ValueError(
            f"{name} must have shape (B, 1, H, W) or (B, H, W), got the 2-D shape {tuple(image.shape)}, which could be "
            f"one (H, W) image or (B, N) flat samples: pass one image as {name}[None, None] (1, 1, H, W), flat samples "
            f"as {name}[:, None] (B, 1, N)"
        )
    raise ValueError(f"{name} must have shape (B, 1, H, W) or (B, H, W), got shape {tuple(image.shape)}")


def flatten_image(name: str, image: Tensor) -> Tensor:
    """``(B, 1, H, W)`` or ``(B, H, W)`` to ``(B, N)``."""
    check_floating(name, image)
    spatial_shape(name, image)
    check_not_empty(name, image)
    return image.reshape(image.shape[0], -1)


def broadcast_map(name: str, values: Tensor, like: Tensor, like_name: str = "captured") -> Tensor:
    """A per-pixel map (variance or mask) given per image or per sample, as ``(1, N)`` or ``(B, N)``.

    Accepted: the spatial shape of ``like`` (``(H, W)``), that shape behind leading ones (``(1, 1, H, W)``), or one
    map per sample (``(B, 1, H, W)``, ``(B, H, W)``); for flat samples ``(B, 1, N)`` also ``(N,)`` and ``(B, N)``.
    """
    check_tensor(name, values)
    check_real_data(name, values)
    spatial = spatial_shape(like_name, like)
    batch = like.shape[0]

    def fits(pixels: tuple[int, ...]) -> bool:
        leading = tuple(values.shape[: values.ndim - len(pixels)])
        per_sample_ok = leading in ((batch,), (batch, 1)) if like.ndim == 4 else leading == (batch,)
        shared_ok = all(size == 1 for size in leading)
        return (
            values.ndim >= len(pixels)
            and tuple(values.shape[values.ndim - len(pixels) :]) == pixels
            and (shared_ok or per_sample_ok)
        )

    # Flat samples (B, 1, N) take their maps as (N,) or (B, N) too: beside a 3-D or 4-D like, that is unambiguous.
    if not (fits(spatial) or (spatial[0] == 1 and fits(spatial[1:]))):
        raise ValueError(
            f"{name} must have the spatial shape of {like_name} {spatial}, optionally behind leading ones or one map "
            f"per sample (batch {batch}), got shape {tuple(values.shape)} for {like_name} of shape {tuple(like.shape)}"
        )
    pixels = math.prod(spatial)
    rows = values.numel() // pixels if pixels else math.prod(values.shape[: values.ndim - len(spatial)])
    return values.reshape(rows, pixels)


def scalar_or_map(name: str, values: Tensor | float, like: Tensor) -> Tensor:
    """Like :func:`broadcast_map`, but a Python number or a 0-d tensor stands for a constant map."""
    if isinstance(values, (int, float)) and not isinstance(values, bool):
        return torch.full((1, 1), float(values), dtype=like.dtype, device=like.device)
    check_floating(name, values)
    if values.ndim == 0:
        return values.reshape(1, 1)
    return broadcast_map(name, values, like)


def mask_map(name: str, mask: Any, like: Tensor, like_name: str = "captured", *, require_pixels: bool = True) -> Tensor:
    """A bool mask given as :func:`broadcast_map` accepts, as ``(B, N)`` for ``like``'s batch ``B`` (a view).

    Raises ``TypeError`` unless it is a bool tensor and, with ``require_pixels``, ``ValueError`` if a sample selects
    no pixel.
    """
    check_bool_mask(name, mask)
    valid = broadcast_map(name, mask, like, like_name).to(like.device).expand(like.shape[0], -1)
    if require_pixels:
        check_mask_not_empty(name, valid)
    return valid


def variance_map(name: str, variance: Tensor | float, like: Tensor, dtype: torch.dtype, valid: Tensor | None) -> Tensor:
    """A variance given as :func:`scalar_or_map` accepts, as ``(B, N)`` in ``dtype``, > 0 where ``valid``, 1 elsewhere.

    ``valid`` is ``None`` (every pixel) or a bool ``(B, N)``.
    """
    number = isinstance(variance, (int, float)) and not isinstance(variance, bool)
    if number:
        check_variance_fits(name, float(variance), dtype)  # before the cast, which would make it 0 or inf
        variance = torch.tensor(float(variance), dtype=dtype, device=like.device)
    given = scalar_or_map(name, variance, like).expand(like.shape[0], like[0].numel())
    if not number:
        check_variance_fits(name, given, dtype, valid)
    flat = given.to(dtype)
    check_positive_where(name, flat, valid)
    return flat if valid is None else torch.where(valid, flat, 1.0)
