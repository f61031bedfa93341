"""ECR, the enhanced (noise-aware) correlation ratio: a Gaussian log-likelihood ratio with per-pixel noise variance.

Model: the sensor sees a function of the map, blurred by noise whose variance is known per pixel. A captured pixel
``v_n`` over a reference pixel in bin ``j_n`` is ``v_n ~ N(mu_{j_n}, sigma_n^2 + tau^2)``, one unknown mean per
reference bin (any response, monotonic or not), ``sigma_n^2`` the pixel's noise variance (analytic or learned) and
``tau^2`` the model variance (what a bin of the map does not explain; by default the spread of an amplitude
uniform in a bin, ``bin_width^2 / 12``). The alternative is one mean for all pixels (captured independent of the
map). With weights ``w_n = 1 / (sigma_n^2 + tau^2)`` and per-bin sums ``W_j = sum w_n``, ``S_j = sum w_n v_n``, the
maximised log-likelihood ratio is

    ``LLR = (sum_j S_j^2 / W_j - S^2 / W) / 2`` (``S``, ``W`` the sums over all bins),

the weighted between-bin sum of squares (generalised least squares). When the captured values are noise of the
stated variances around one level, ``2 LLR`` is ``chi^2`` with ``K_occ - 1`` degrees of freedom (``K_occ`` the
occupied reference bins) whatever the variances, so ``ECR = (LLR - (K_occ - 1) / 2) / n`` (``n`` the valid pixels)
has mean 0; a captured image with structure of its own that is unrelated to the reference scores about
``(K_occ - 1) / (2 n)`` times its spread over the noise variance, small against an aligned placement's score and
without a term that follows the map's content. A noisy pixel adds its evidence in proportion to its precision
instead of a full unit of histogram weight, which is what makes the per-pixel variance pay (see
``data_tools/yardstick.py`` and ``data_tools/diagnose_enmi.py``).

With one variance for all pixels, ``ECR = eta^2 Var[v] / (2 (sigma^2 + tau^2)) - (K_occ - 1) / (2 n)`` with
``eta^2`` the classic correlation ratio (Pearson, Roche et al. 1998) of the captured image given the reference bins.

Convention:
    Captured values are used as they are (not clipped: a value beyond the range is still evidence); reference values
    are hard-binned into ``bins`` equal bins over ``value_range``, clipped into the edge bins.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from enmi_torch._checks import check_floating, check_option, check_variance_given
from enmi_torch.binning import bin_width, hard_bin_index
from enmi_torch.histogram import _prepare


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


RESPONSES = ("binned", "linear")


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


def default_model_variance(bins: int, value_range: tuple[float, float]) -> float:
    """``bin_width^2 / 12``: the variance of an amplitude uniform in one reference bin.

    Example:
        >>> default_model_variance(32, (0.0, 256.0))
        5.333333333333333
    """
    return bin_width(bins, value_range) ** 2 / 12


def check_model_variance(model_variance, bins: int, value_range: tuple[float, float]) -> float:
    """``model_variance`` as a float >= 0; ``None`` gives :func:`default_model_variance`."""
    if model_variance is None:
        return default_model_variance(bins, value_range)
    if isinstance(model_variance, bool) or not isinstance(model_variance, (int, float)) or not model_variance >= 0:
        raise ValueError(f"model_variance must be a number >= 0 or None, got {model_variance!r}")
    if model_variance == float("inf"):
        raise ValueError("model_variance must be finite, got inf")
    return float(model_variance)


def ecr_from_bin_sums(sums: BinSums) -> Tensor:
    """ECR from per-bin sums ``(..., bins)`` (summed over batches or processes if need be), ``(...)``.

    Bins with no valid pixel are left out (``0 / 0``); a placement without any valid pixel scores 0.

    Example:
        >>> sums = BinSums(torch.tensor([[2.0, 2.0]]), torch.tensor([[2.0, 2.0]]), torch.tensor([[-4.0, 4.0]]))
        >>> ecr_from_bin_sums(sums)  # (16 / 2 + 16 / 2 - 0) / 2 = 8 nats, minus 1 / 2 for 2 bins, over 4 pixels
        tensor([1.8750])
    """
    return _ecr_from_sums(sums.count, sums.weight, sums.weighted_value, -1)


def _ecr_from_sums(
    count: Tensor, weight: Tensor, weighted_value: Tensor, dim: int, total_count: Tensor | None = None
) -> Tensor:
    """:func:`ecr_from_bin_sums` with the bins along ``dim`` (the score surfaces keep them first).

    ``total_count``: the valid pixels, when ``count`` only marks the occupied bins (``count.sum(dim)`` otherwise).
    """
    occupied = count > 0.5
    safe_weight = torch.where(occupied, weight, 1.0)
    between = torch.where(occupied, weighted_value.square() / safe_weight, 0.0).sum(dim)
    total_weight = weight.sum(dim)
    between = between - weighted_value.sum(dim).square() / total_weight.clamp_min(torch.finfo(between.dtype).tiny)
    if total_count is None:
        total_count = count.sum(dim)
    penalty = (occupied.sum(dim) - 1).clamp_min(0).to(between.dtype)
    return torch.where(total_count > 0.5, 0.5 * (between - penalty) / total_count.clamp_min(1), 0.0)


def ecr(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    model_variance: float | None = None,
    valid_mask: Tensor | None = None,
    response: str = "binned",
) -> Tensor:
    """Enhanced correlation ratio: the noise-aware Gaussian log-likelihood ratio per valid pixel, in nats, ``(B,)``.

    Args:
        captured: noisy image ``(B, 1, H, W)``, ``(B, H, W)`` or ``(B, N)``, floating point.
        reference: noiseless map section, same shape; or ``(C, *captured.shape)``, ``C`` candidates per image.
        variance: per-pixel noise variance of ``captured`` (> 0 where valid): a number, ``(H, W)``,
            ``(1, 1, H, W)`` or ``(B, 1, H, W)``.
        bins: number of equal-width bins the reference is cut into, over ``value_range``.
        value_range: ``(low, high)`` of the reference bins.
        model_variance: ``tau^2 >= 0`` added to every pixel's variance (see the module docstring); ``None`` for
            ``bin_width^2 / 12``.
        valid_mask: bool, broadcast like ``variance``; ``False`` pixels are left out (they may hold NaN).
        response: the sensor's response to the map: ``"binned"`` (one mean per reference bin: any function,
            monotonic or not; the default) or ``"linear"`` (``a + b r`` with ``b > 0``, the reference values
            themselves: the noise-aware form of normalised cross-correlation, with a penalty of one degree of
            freedom; ``bins`` only check that the reference is resolved).

    Returns:
        ECR ``(B,)`` (``(C, B)`` for candidates), same dtype as ``captured``: larger the better the reference bins
        predict the captured values, small for unrelated images (0 on average for pure noise); ``ECR * n`` is the
        log-likelihood ratio less its mean for pure noise.

    Convention:
        Differentiable in ``captured`` and ``variance`` (the reference is hard-binned).

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 16, 16, generator=generator) * 256
        >>> captured = reference + 8 * torch.randn(1, 1, 16, 16, generator=generator)
        >>> ecr(captured, torch.stack([reference, reference.roll(1, -1)]), 64.0, bins=8)
        tensor([[17.4752],
                [ 0.4031]])
    """
    check_variance_given(variance)
    check_floating("captured", captured)
    inputs = _prepare(
        captured, reference, bins, value_range, variance, valid_mask, "mass", "hard", None, "variance", False
    )
    tau2 = check_model_variance(model_variance, inputs.bins, inputs.value_range)
    check_option("response", response, RESPONSES)
    if response == "linear":
        score = _linear_ecr(inputs.captured, inputs.reference, inputs.variance + tau2, inputs.pair_weight)
        return (score if inputs.with_candidates else score[0]).to(inputs.out_dtype)
    sums = bin_sums(
        inputs.captured, inputs.reference, inputs.variance + tau2, inputs.pair_weight, inputs.bins, inputs.value_range
    )
    score = ecr_from_bin_sums(sums)
    return (score if inputs.with_candidates else score[0]).to(inputs.out_dtype)


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


def _linear_ecr(captured: Tensor, reference: Tensor, total_variance: Tensor, valid: Tensor | None) -> Tensor:
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
