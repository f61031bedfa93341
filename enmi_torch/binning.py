"""Amplitude bins and the weights a pixel gives them: hard, Parzen windows, and Gaussian likelihoods.

Convention:
    ``bins`` equal-width bins cover ``value_range = (low, high)``: bin ``i`` is ``[low + i w, low + (i + 1) w)`` with
    ``w = (high - low) / bins`` and centre ``low + (i + 0.5) w``. Values outside the range are clipped into it (they
    count in the edge bins), as a sensor saturates.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from enmi_torch.utils.checks import (
    check_bins,
    check_finite_where,
    check_floating,
    check_option,
    check_positive_number,
    check_positive_where,
    check_value_range,
)

PARZEN_KERNELS = ("hard", "triangular", "xu")
LIKELIHOOD_WEIGHTS = ("mass", "density", "truncated")

# Below this standard deviation (in bin widths) a likelihood is already a unit count in float64; clamping the
# variance here keeps (c - v)^2 / var^2 finite in gradients.
_MIN_STD_IN_BINS = 1e-6
# The derivatives' exp(-z^2 / 2) is clamped at e^-80 (1.8e-35, nothing next to the sums it enters): float32 exp
# takes a slow path where its result is denormal (below about e^-87).
_EXP_FLOOR = -80.0


def bin_width(bins: int, value_range: tuple[float, float]) -> float:
    """Width of one of ``bins`` equal bins over ``value_range``."""
    return (value_range[1] - value_range[0]) / bins


def bin_edges(bins: int, value_range: tuple[float, float], *, dtype=None, device=None) -> Tensor:
    """The ``bins + 1`` edges of the bins, ``(bins + 1,)``.

    Example:
        >>> bin_edges(4, (0.0, 8.0))
        tensor([0., 2., 4., 6., 8.])
    """
    low, high = check_value_range(value_range)
    check_bins(bins)
    return torch.linspace(low, high, bins + 1, dtype=dtype, device=device)


def bin_centers(bins: int, value_range: tuple[float, float], *, dtype=None, device=None) -> Tensor:
    """The ``bins`` bin centres, ``(bins,)``.

    Example:
        >>> bin_centers(4, (0.0, 8.0))
        tensor([1., 3., 5., 7.])
    """
    width = bin_width(bins, value_range)
    return value_range[0] + width * (torch.arange(bins, dtype=dtype, device=device) + 0.5)


def hard_bin_index(values: Tensor, bins: int, value_range: tuple[float, float]) -> Tensor:
    """Index of the bin holding each value, clipped into ``[0, bins - 1]``; same shape as ``values``, int64.

    Example:
        >>> hard_bin_index(torch.tensor([-3.0, 0.0, 1.99, 2.0, 7.9, 100.0]), 4, (0.0, 8.0))
        tensor([0, 0, 0, 1, 3, 3])
    """
    scaled = (values - value_range[0]) * (bins / (value_range[1] - value_range[0]))
    return scaled.floor().clamp(0, bins - 1).long()


def parzen_weights(values: Tensor, bins: int, value_range: tuple[float, float], kernel: str) -> Tensor:
    """Weights ``(..., bins)`` that each value gives the bins under a Parzen window; each row sums to 1.

    Args:
        values: any shape ``(...)``.
        bins: number of bins.
        value_range: ``(low, high)``.
        kernel: ``"hard"`` (one-hot, no gradient), ``"triangular"`` (linear interpolation between the two nearest
            bin centres, the classic soft histogram) or ``"xu"`` (the second-order polynomial window of Xu et al.
            2008, also kornia's default, support of one bin width on each side).

    Convention:
        Distances are measured in bin widths from the bin centres; values are clipped to the outer bin centres so
        that every row sums to 1 (the edge half-bins count fully in the edge bins).

    Example:
        >>> parzen_weights(torch.tensor([2.0]), 4, (0.0, 8.0), "triangular")
        tensor([[0.5000, 0.5000, 0.0000, 0.0000]])
    """
    check_floating("values", values)
    check_option("kernel", kernel, PARZEN_KERNELS)
    check_finite_where("values", values, None)
    return parzen_weights_unchecked(values, check_bins(bins), check_value_range(value_range), kernel)


def parzen_weights_unchecked(values: Tensor, bins: int, value_range: tuple[float, float], kernel: str) -> Tensor:
    """:func:`parzen_weights` without its checks, for callers that checked the arguments once (the histograms).

    ``values`` floating point and finite, ``bins`` and ``value_range`` as :func:`~enmi_torch.utils.checks.check_bins`
    and :func:`~enmi_torch.utils.checks.check_value_range` return them, ``kernel`` one of :data:`PARZEN_KERNELS`.

    Example:
        >>> parzen_weights_unchecked(torch.tensor([2.0]), 4, (0.0, 8.0), "hard")
        tensor([[0., 1., 0., 0.]])
    """
    if kernel == "hard":
        index = hard_bin_index(values, bins, value_range)
        return torch.nn.functional.one_hot(index, bins).to(values.dtype)
    width = bin_width(bins, value_range)
    position = ((values - value_range[0]) / width - 0.5).clamp(0, bins - 1)
    distance = (position.unsqueeze(-1) - torch.arange(bins, dtype=values.dtype, device=values.device)).abs()
    if kernel == "triangular":
        return (1 - distance).clamp_min(0)
    inner = 1 - distance * (0.1 + 1.8 * distance)
    outer = (1.9 - distance * (3.7 - 1.8 * distance)).clamp_min(0)  # rounding leaves -2e-16 at distance 1
    return torch.where(distance < 0.5, inner, torch.where(distance <= 1, outer, torch.zeros_like(distance)))


def min_variance(bins: int, value_range: tuple[float, float]) -> float:
    """The variance below which a Gaussian likelihood is treated as a unit count (clamped to this value)."""
    return (_MIN_STD_IN_BINS * bin_width(bins, value_range)) ** 2


def likelihood_weights(
    values: Tensor,
    variance: Tensor,
    bins: int,
    value_range: tuple[float, float],
    kernel: str = "mass",
    log_prior: Tensor | None = None,
) -> Tensor:
    """Weights ``(..., bins)`` that a noisy value gives the bins under its Gaussian likelihood; rows sum to 1.

    Args:
        values: observed values ``v``, any shape ``(...)``.
        variance: noise variance ``sigma^2`` of each value, broadcastable to ``values``, > 0.
        bins: number of bins.
        value_range: ``(low, high)``.
        kernel: ``"mass"``: the probability ``N(v, sigma^2)`` puts in each bin, the tails folded into the edge
            bins (the paper's ENMI); ``"density"``: the Gaussian density at the bin centres, normalised over the
            bins; ``"truncated"``: the masses inside the range only, renormalised (the bins' likelihoods, see
            :func:`truncated_likelihood_weights`; a noisy value near an edge no longer piles its tail there).
        log_prior: optional ``(bins,)`` or ``(B, bins)``-broadcastable log prior of the amplitude per bin; the
            weights become the posterior (likelihood times prior, normalised), the MAP view of the paper.

    Convention:
        Differentiable in ``values`` and ``variance``. Variances below :func:`min_variance` are clamped to it (the
        weights are a unit count there already).

    Example:
        >>> w = likelihood_weights(torch.tensor([3.0]), torch.tensor([1.0]), 4, (0.0, 8.0))
        >>> [round(x, 4) for x in w[0].tolist()]
        [0.1587, 0.6827, 0.1573, 0.0013]
    """
    check_floating("values", values)
    check_floating("variance", variance)
    check_option("kernel", kernel, LIKELIHOOD_WEIGHTS)
    check_finite_where("values", values, None)
    check_positive_where("variance", variance, None)
    bins, value_range = check_bins(bins), check_value_range(value_range)
    return likelihood_weights_unchecked(values, variance, bins, value_range, kernel, log_prior)


def likelihood_weights_unchecked(
    values: Tensor,
    variance: Tensor,
    bins: int,
    value_range: tuple[float, float],
    kernel: str = "mass",
    log_prior: Tensor | None = None,
) -> Tensor:
    """:func:`likelihood_weights` without its checks, for callers that checked the arguments once (the histograms).

    ``values`` floating point and finite, ``variance`` > 0, ``bins`` and ``value_range`` checked, ``kernel`` one of
    :data:`LIKELIHOOD_WEIGHTS`, ``log_prior`` broadcastable to ``(..., bins)``. Differentiable in ``values`` and
    ``variance``.
    """
    if kernel == "truncated":
        log_weights = _log_bin_masses(values, variance, bins, value_range)
        return torch.softmax(log_weights if log_prior is None else log_weights + log_prior, dim=-1)
    variance = variance.clamp_min(min_variance(bins, value_range))
    if kernel == "mass":
        interior = bin_edges(bins, value_range, dtype=values.dtype, device=values.device)[1:-1]
        std = variance.sqrt().unsqueeze(-1)
        cdf = 0.5 * (1 + torch.erf((interior - values.unsqueeze(-1)) / (std * math.sqrt(2))))
        mass = torch.cat([cdf[..., :1], cdf[..., 1:] - cdf[..., :-1], 1 - cdf[..., -1:]], dim=-1)
        if log_prior is None:
            return mass
        # Posterior in log space: likelihood times prior can underflow where the prior is tiny.
        tiny = torch.finfo(mass.dtype).tiny ** 0.5
        return torch.softmax(mass.clamp_min(tiny).log() + log_prior, dim=-1)
    centers = bin_centers(bins, value_range, dtype=values.dtype, device=values.device)
    score = -((centers - values.unsqueeze(-1)) ** 2) / (2 * variance.unsqueeze(-1))
    if log_prior is not None:
        score = score + log_prior
    return torch.softmax(score, dim=-1)


def truncated_likelihood_weights(
    values: Tensor, variance: Tensor, bins: int, value_range: tuple[float, float]
) -> Tensor:
    """Weights ``(..., bins)``: the mass ``N(v, sigma^2)`` puts in each bin, truncated to the range; rows sum to 1.

    Unlike the ``"mass"`` weights of :func:`likelihood_weights`, the tails outside ``[low, high)`` are dropped, not
    folded into the edge bins, and the masses are normalised over the bins. For an amplitude uniform in bin ``i``
    observed with noise ``N(0, sigma^2)``, the density of ``v`` is proportional to the mass ``N(v, sigma^2)`` puts in
    bin ``i``: the weights are the bins' likelihoods, up to a factor per value.

    Args:
        values: observed values ``v``, any shape ``(...)``.
        variance: noise variance ``sigma^2`` of each value, broadcastable to ``values``, > 0.
        bins: number of bins.
        value_range: ``(low, high)``.

    Convention:
        Computed in log space (an ``erf`` difference within a standard deviation of the value, a ``log_ndtr``
        difference beyond), so values far outside the range and tiny variances stay finite: a value far above the range
        gives its weight to the top bin. Differentiable in ``values`` and ``variance``; variances below
        :func:`min_variance` are clamped to it, values to ``max(8 sigma, 64 sigma^2 / bin width)`` outside the range
        (one-hot weights there and beyond, to e^-64).

    Example:
        >>> w = truncated_likelihood_weights(torch.tensor([3.0, 1e6]), torch.tensor([1.0, 1.0]), 4, (0.0, 8.0))
        >>> [[round(x, 4) for x in row] for row in w.tolist()]
        [[0.1575, 0.6836, 0.1575, 0.0014], [0.0, 0.0, 0.0, 1.0]]
    """
    return torch.softmax(_log_bin_masses(values, variance, bins, value_range), dim=-1)


def _log_bin_masses(values: Tensor, variance: Tensor, bins: int, value_range: tuple[float, float]) -> Tensor:
    """``log P(edge_i <= X < edge_i+1)`` for ``X ~ N(v, sigma^2)``, ``(..., bins)``, finite for any finite input."""
    low, high = value_range
    std = variance.clamp_min(min_variance(bins, value_range)).sqrt()
    # Beyond this margin outside the range, neighbouring bins' masses differ by more than e^64: the weights are one-hot
    # to float precision, and clamping the value there keeps z^2 finite for any value.
    margin = std.detach() * torch.clamp_min(64 * std.detach() / bin_width(bins, value_range), 8)
    values = torch.minimum(torch.maximum(values, low - margin), high + margin)
    edges = bin_edges(bins, value_range, dtype=values.dtype, device=values.device)
    standardized = (edges - values.unsqueeze(-1)) / std.unsqueeze(-1)
    lower, upper = standardized[..., :-1], standardized[..., 1:]
    tiny = torch.finfo(values.dtype).tiny
    # Two forms, each where it is precise, each computed once per edge. Within a standard deviation of the value (or
    # across it), an erf difference, free of the cancellation a log_ndtr difference has there; the clamp keeps a
    # rounded-off 0 finite (an interval below eps standard deviations: a flat likelihood anyway).
    erf_edges = torch.erf(standardized * math.sqrt(0.5))
    near_log = torch.log((erf_edges[..., 1:] - erf_edges[..., :-1]).clamp_min(tiny)) - math.log(2)
    # Beyond, where masses underflow, a log_ndtr difference on the value's side (P(a < X < b) = P(-b < X < -a)):
    # Phi(-|z|) of the edge nearer the value less that of the farther one.
    tail_edges = _LowerLogNdtr.apply(-standardized.abs())
    above = lower > 0
    log_inner = torch.where(above, tail_edges[..., :-1], tail_edges[..., 1:])
    log_outer = torch.where(above, tail_edges[..., 1:], tail_edges[..., :-1])
    far_log = log_inner + torch.log(-torch.expm1((log_outer - log_inner).clamp_max(-tiny)))
    return torch.where((upper > -1) & (lower < 1), near_log, far_log)


class _LowerLogNdtr(torch.autograd.Function):
    """``log Phi(z)`` for ``z <= 0`` with the derivative ``phi(z) / Phi(z) = sqrt(2 / pi) / erfcx(-z / sqrt(2))``.

    torch's own derivative of ``log_ndtr`` divides two underflowing numbers: NaN in float32 below about z = -1e4
    (variances of 1e-5 grey levels^2 over 8-wide bins), inf in float64 further out; the scaled erfc stays exact.
    """

    @staticmethod
    def forward(standardized: Tensor) -> Tensor:
        return torch.special.log_ndtr(standardized)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:
        ctx.save_for_backward(inputs[0])

    @staticmethod
    def backward(ctx, grad_output: Tensor) -> Tensor:
        (standardized,) = ctx.saved_tensors
        return grad_output * math.sqrt(2 / math.pi) / torch.special.erfcx(standardized * -math.sqrt(0.5))


def gaussian_log_prior(
    mean: float, std: float, bins: int, value_range: tuple[float, float], *, dtype=None, device=None
) -> Tensor:
    """Log of the probability a ``N(mean, std^2)`` amplitude falls in each bin (tails folded), ``(bins,)``.

    The prior the paper's simulation draws its amplitudes from is ``gaussian_log_prior(128, 32, 32, (0, 256))``.

    Example:
        >>> gaussian_log_prior(4.0, 1.0, 4, (0.0, 8.0)).exp().sum().item()
        1.0
    """
    if isinstance(mean, bool) or not isinstance(mean, (int, float)) or not math.isfinite(mean):
        raise ValueError(f"mean must be a finite number, got {mean!r}")
    std = check_positive_number("std", std)
    dtype = dtype or torch.get_default_dtype()
    interior = bin_edges(bins, value_range, dtype=torch.float64, device=device)[1:-1]
    cdf = 0.5 * torch.erfc(-(interior - mean) / (std * math.sqrt(2)))
    mass = torch.cat([cdf[:1], cdf[1:] - cdf[:-1], 1 - cdf[-1:]]).clamp_min(torch.finfo(torch.float64).tiny)
    return (mass / mass.sum()).log().to(dtype)


def likelihood_weights_vjp(
    values: Tensor,
    variance: Tensor,
    upstream: Tensor,
    bins: int,
    value_range: tuple[float, float],
    kernel: str = "mass",
    log_prior: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Vector-Jacobian product of :func:`likelihood_weights`: ``upstream`` ``(..., bins)`` to (d values, d variance).

    Closed-form derivatives (one exp per bin edge or centre, no erf, in-place where possible), used by the chunked
    joint histogram's backward pass; the ``"mass"`` weights with a prior and the ``"truncated"`` weights fall back to
    autograd.
    """
    floor = min_variance(bins, value_range)
    clamped = variance < floor
    variance = variance.clamp_min(floor)
    if kernel == "truncated" or (kernel == "mass" and log_prior is not None):
        with torch.enable_grad():
            values = values.detach().requires_grad_()
            variance = variance.detach().requires_grad_()
            result = likelihood_weights_unchecked(values, variance, bins, value_range, kernel, log_prior)
            grad_values, grad_variance = torch.autograd.grad(result, (values, variance), upstream)
        return grad_values, torch.where(clamped, 0.0, grad_variance)
    if kernel == "mass":
        # d weight_i / d cdf_k is +1 for i = k and -1 for i = k + 1.
        grad_values, grad_variance = mass_weights_vjp(
            values, variance, upstream[..., :-1] - upstream[..., 1:], bins, value_range
        )
        return grad_values, torch.where(clamped, 0.0, grad_variance)
    offset = bin_centers(bins, value_range, dtype=values.dtype, device=values.device) - values.unsqueeze(-1)
    score = offset.square().mul_((-0.5 / variance).unsqueeze(-1))
    if log_prior is not None:
        score = score + log_prior
    probability = torch.softmax(score, dim=-1)
    grad_score = probability.mul_(upstream - torch.linalg.vecdot(probability, upstream).unsqueeze(-1))
    grad_values = torch.linalg.vecdot(grad_score, offset) / variance
    grad_variance = torch.linalg.vecdot(grad_score, offset.square_()) / (2 * variance.square())
    return grad_values, torch.where(clamped, 0.0, grad_variance)


def mass_weights_vjp(
    values: Tensor, variance: Tensor, edge_upstream: Tensor, bins: int, value_range: tuple[float, float]
) -> tuple[Tensor, Tensor]:
    """Vector-Jacobian product of the ``"mass"`` weights, given ``upstream_k - upstream_k+1`` per interior edge.

    The closed form behind :func:`likelihood_weights_vjp` (``"mass"``, no prior), for callers that difference the
    upstream gradient once per histogram row instead of once per pixel; returns ``(d values, d variance)``.

    ``edge_upstream`` ``(..., bins - 1)`` is overwritten; ``variance`` must already be clamped to
    :func:`min_variance` (the caller zeroes the variance gradient where it was). ``d cdf_k / d v = -pdf(z_k) / std``.
    """
    inverse_std = variance.rsqrt()
    interior = bin_edges(bins, value_range, dtype=values.dtype, device=values.device)[1:-1]
    standardized = (interior - values.unsqueeze(-1)).mul_(inverse_std.unsqueeze(-1))
    # -z^2 / 2 in one pass (halving is exact, so these are the bits of -(z * z) / 2).
    exponent = torch.addcmul(standardized.new_zeros(()), standardized, standardized, value=-0.5)
    per_edge = edge_upstream.mul_(exponent.clamp_min_(_EXP_FLOOR).exp_())
    scale = inverse_std * (-1 / math.sqrt(2 * math.pi))
    grad_values = per_edge.sum(-1).mul_(scale)
    grad_variance = torch.linalg.vecdot(per_edge, standardized).mul_(scale).mul_(0.5 * inverse_std)
    return grad_values, grad_variance


def reliability_weights(values: Tensor, variance: Tensor, valid: Tensor | None = None) -> Tensor:
    """Reliability ``s^2 / (s^2 + sigma_n^2)`` of each noisy value ``(B, N)``: the share of its variance that is signal.

    ``s^2`` is each sample's signal variance, estimated from the values themselves: their variance over the valid
    pixels less the mean noise variance (method of moments), at least 1 % of the value variance. The weights are
    1 for noiseless pixels, equal for equal noise (so a uniform variance changes no normalised score), and fall as
    ``1 / sigma^2`` for the noisiest. Not differentiated (a data-derived constant).

    Args:
        values: ``(B, N)`` noisy values.
        variance: ``(B, N)`` or ``(1, N)`` noise variances, > 0 where valid.
        valid: optional bool ``(B, N)``; invalid pixels get weight 0 and are left out of ``s^2``.

    Example:
        >>> values = torch.tensor([[0.0, 10.0, 20.0, 30.0]])
        >>> reliability_weights(values, torch.tensor([[1.0, 1.0, 100.0, 100.0]]))
        tensor([[0.9868, 0.9868, 0.4269, 0.4269]])
    """
    with torch.no_grad():
        weight = torch.ones_like(values) if valid is None else valid.to(values.dtype)
        count = weight.sum(-1, keepdim=True).clamp_min(1)
        mean = (weight * values).sum(-1, keepdim=True) / count
        spread = (weight * (values - mean).square()).sum(-1, keepdim=True) / count
        noise = (weight * variance).sum(-1, keepdim=True) / count
        signal = (spread - noise).clamp_min(0.01 * spread).clamp_min(torch.finfo(values.dtype).tiny)
        return weight * signal / (signal + variance)
