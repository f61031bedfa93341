"""ECR from its sufficient statistics: per-bin sums (binned and shrunk responses), weighted moments (linear one).

With weights ``w_n = 1 / (sigma_n^2 + tau^2)`` and per-bin sums ``W_j = sum w_n``, ``S_j = sum w_n v_n`` (a
:class:`BinSums`, which can be summed over batches or processes), the binned response's log-likelihood ratio is
``(sum_j S_j^2 / W_j - S^2 / W) / 2`` and ECR is that less ``(K_occ - 1) / 2``, over the valid pixels
(:func:`ecr_from_bin_sums`); the shrunk response's comes from the same sums
(:mod:`~enmi_torch.scores.shrunk_response`). The linear response ``a + b r`` needs the weighted moments of the values
and the reference instead (:func:`linear_llr`).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from enmi_torch.binning import hard_bin_index
from enmi_torch.scores.ecr_model_variance import RESPONSE_VARIANCE_ESTIMATE
from enmi_torch.scores.ecr_options import RESPONSES, check_ecr_options
from enmi_torch.scores.shrunk_response import bin_positions, shrunk_llr, shrunk_llr_terms
from enmi_torch.utils.checks import check_option
from enmi_torch.utils.options import signature_defaults


class BinSums(NamedTuple):
    """Per reference bin sums of one placement, ``(..., bins)`` each: the streaming state of ECR.

    Attributes:
        count: valid pixels ``n_j``.
        weight: ``W_j = sum w_n``.
        weighted_value: ``S_j = sum w_n v_n`` (values centred on a constant; ECR does not depend on it).
    """

    count: Tensor
    weight: Tensor
    weighted_value: Tensor


def linear_llr(
    weight: Tensor,
    weighted_value: Tensor,
    weighted_reference: Tensor,
    weighted_square: Tensor,
    weighted_product: Tensor,
) -> Tensor:
    """Log-likelihood ratio of an increasing affine response from weighted sums (any shape), 0 for a falling one.

    With ``W = sum w``, ``S_v = sum w v``, ``S_r = sum w r``, ``S_rr = sum w r^2`` and ``S_vr = sum w v r`` over the
    valid pixels, the generalised-least-squares fit of ``v = a + b r`` explains ``(S_vr - S_v S_r / W)^2 /
    (S_rr - S_r^2 / W)`` of the weighted sum of squares; half of it is the log-likelihood ratio against ``v = a``.
    A placement where ``b <= 0`` (inverted contrast) or the reference is constant scores 0.
    """
    tiny = torch.finfo(weight.dtype).tiny
    safe = weight.clamp_min(tiny)
    covariance = weighted_product - weighted_value * weighted_reference / safe
    spread = weighted_square - weighted_reference.square() / safe
    defined = (spread > 64 * torch.finfo(weight.dtype).eps * weighted_square.abs()) & (covariance > 0)
    return torch.where(defined, 0.5 * covariance.square() / torch.where(defined, spread, 1.0), 0.0)


def bin_sums(
    captured: Tensor,
    reference: Tensor,
    total_variance: Tensor,
    valid: Tensor | None,
    bins: int,
    value_range: tuple[float, float],
    centre: Tensor | float | None = None,
) -> BinSums:
    """Per-bin sums of ``(B, N)`` captured values over ``(C, B, N)`` references, ``(C, B, bins)`` each.

    ``total_variance`` is ``sigma^2 + tau^2`` ``(B, N)``; ``valid`` ``(B, N)`` float 0/1 or ``None``. Values are
    centred on ``centre`` (``(B, 1)`` or a number; ``None``: each sample's weighted mean), which keeps
    ``S_j^2 / W_j - S^2 / W`` free of cancellation; ECR does not depend on it, but sums accumulated over several
    calls (streaming) must share one centre.
    """
    weight = total_variance.reciprocal()
    if valid is not None:
        weight = weight * valid
    if centre is None:
        centre = (weight * captured).sum(-1, keepdim=True).detach() / weight.sum(-1, keepdim=True).detach()
    weighted_value = weight * (captured - centre)
    count = torch.ones_like(captured) if valid is None else valid
    samples = reference.shape[:-1]
    offsets = torch.arange(samples.numel(), device=captured.device).view(*samples, 1) * bins
    cells = (hard_bin_index(reference, bins, value_range) + offsets).flatten()
    sums = []
    for per_pixel in (count, weight, weighted_value):
        source = per_pixel.expand(reference.shape).reshape(-1)
        sums.append(per_pixel.new_zeros(samples.numel() * bins).index_add(0, cells, source).view(*samples, bins))
    return BinSums(*sums)


def linear_ecr(captured: Tensor, reference: Tensor, total_variance: Tensor, valid: Tensor | None) -> Tensor:
    """ECR of the increasing affine response for ``(B, N)`` captured values over ``(C, B, N)`` references."""
    weight = total_variance.reciprocal()
    if valid is not None:
        weight = weight * valid
    count = (torch.ones_like(captured) if valid is None else valid).sum(-1)
    # Centring both images keeps the sums free of cancellation; the score does not depend on the centres.
    total = weight.sum(-1, keepdim=True)
    value = captured - ((weight * captured).sum(-1, keepdim=True) / total).detach()
    centred = reference - ((weight * reference).sum(-1, keepdim=True) / total).detach()
    sums = (
        weight.sum(-1).expand(centred.shape[:-1]),
        (weight * value).sum(-1).expand(centred.shape[:-1]),
        (weight * centred).sum(-1),
        (weight * centred.square()).sum(-1),
        (weight * value * centred).sum(-1),
    )
    return (linear_llr(*sums) - 0.5) / count.clamp_min(1)


def ecr_from_bin_sums(
    sums: BinSums,
    *,
    response: str = "shrunk",
    value_range: tuple[float, float] = (0.0, 256.0),
    response_variance: float | str | Tensor = "estimate",
) -> Tensor:
    """ECR from per-bin sums ``(..., bins)`` (summed over batches or processes if need be), ``(...)``.

    Bins with no valid pixel are left out (``0 / 0``); a placement without any valid pixel scores 0. ``response``:
    ``"shrunk"`` (the default, as :func:`~enmi_torch.scores.ecr.ecr`'s) or ``"binned"``; ``value_range``: the bins'
    range (the scale of the shrunk response's ``delta^2`` grid; the binned response does not use it);
    ``response_variance``: the shrunk response's ``delta^2``, ``"estimate"`` (each set of sums its own, where its
    profile is largest, held fixed in the gradient; the pixels taken as independent) or a number (or a tensor
    broadcastable to ``(...)``), refused with the binned response (:data:`~enmi_torch.scores.ecr_options.ECR_RULES`).

    Example:
        >>> sums = BinSums(torch.tensor([[2.0, 2.0]]), torch.tensor([[2.0, 2.0]]), torch.tensor([[-4.0, 4.0]]))
        >>> ecr_from_bin_sums(sums, response="binned")  # (16 / 2 + 16 / 2 - 0) / 2 = 8 nats, less 1 / 2, over 4 pixels
        tensor([1.8750])
        >>> ecr_from_bin_sums(sums, value_range=(0.0, 2.0))  # two bins: the line through them fits, no deviation
        tensor([1.8750])
    """
    check_option("response", response, RESPONSES[:2])
    options = {"response": response, "response_variance": response_variance}
    response_variance = check_ecr_options(options, signature_defaults(ecr_from_bin_sums))["response_variance"]
    positions = bin_positions(sums.weight.shape[-1], sums.weight.dtype, sums.weight.device)
    shrunk = None if response == "binned" else (positions, value_range, response_variance)
    return ecr_from_sums(sums.count, sums.weight, sums.weighted_value, -1, shrunk=shrunk)


def ecr_from_sums(
    count: Tensor,
    weight: Tensor,
    weighted_value: Tensor,
    dim: int,
    total_count: Tensor | None = None,
    shrunk: tuple[Tensor, tuple[float, float], float | str | Tensor] | None = None,
) -> Tensor:
    """:func:`ecr_from_bin_sums` with the bins along ``dim`` (the score surfaces keep them first).

    ``total_count``: the valid pixels, when ``count`` only marks the occupied bins (``count.sum(dim)`` otherwise).
    ``shrunk``: the bins' positions ``u_j`` (along ``dim``), the value range and ``delta^2`` (``"estimate"`` for each
    placement's profile maximum, or a number or tensor broadcastable to the result), for the shrunk response;
    ``None`` for the binned one.
    """
    occupied = count > 0.5
    if total_count is None:
        total_count = count.sum(dim)
    if shrunk is not None:
        positions, value_range, response_variance = shrunk
        shape = [1] * weight.dim()
        shape[dim] = -1
        weight = torch.where(occupied, weight, 0.0).movedim(dim, 0)
        weighted_value = torch.where(occupied, weighted_value, 0.0).movedim(dim, 0)
        positions = positions.to(weight.dtype).view(shape).movedim(dim, 0)
        if response_variance == RESPONSE_VARIANCE_ESTIMATE:  # held fixed in the gradient, as everywhere
            with torch.no_grad():
                _, response_variance = shrunk_llr(weight, weighted_value, positions, value_range)
        if isinstance(response_variance, Tensor):
            response_variance = response_variance.to(weight.dtype).expand(weight.shape[1:])
        llr = shrunk_llr_terms(weight, weighted_value, positions, response_variance)
        return torch.where(total_count > 0.5, (llr - 0.5) / total_count.clamp_min(1), 0.0)
    safe_weight = torch.where(occupied, weight, 1.0)
    between = torch.where(occupied, weighted_value.square() / safe_weight, 0.0).sum(dim)
    total_weight = weight.sum(dim)
    between = between - weighted_value.sum(dim).square() / total_weight.clamp_min(torch.finfo(between.dtype).tiny)
    penalty = (occupied.sum(dim) - 1).clamp_min(0).to(between.dtype)
    return torch.where(total_count > 0.5, 0.5 * (between - penalty) / total_count.clamp_min(1), 0.0)
