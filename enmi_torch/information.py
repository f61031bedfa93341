"""Normalized mutual information (Studholme) and its noise-aware form ENMI, from joint histograms."""

from __future__ import annotations

import torch
from torch import Tensor

from enmi_torch._checks import check_floating, check_option, check_variance_given
from enmi_torch.binning import LIKELIHOOD_WEIGHTS, reliability_weights
from enmi_torch.histogram import _joint_histogram, _prepare, hard_entropies


def entropies(counts: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Entropies ``(H[A], H[B], H[A, B])`` in nats of a joint histogram ``(B, K, K)`` (captured on axis 1).

    Convention:
        ``0 log 0 = 0``; empty bins give finite values and gradients. A sample whose counts are all zero has all
        three entropies 0.

    Example:
        >>> counts = torch.tensor([[[1.0, 0.0], [0.0, 1.0]]])
        >>> [round(h.item(), 4) for h in entropies(counts)]
        [0.6931, 0.6931, 0.6931]
    """
    total = counts.sum(dim=(-2, -1), keepdim=True)
    probability = counts / total.clamp_min(torch.finfo(counts.dtype).tiny)
    return (
        _entropy(probability.sum(dim=-1), dims=(-1,)),
        _entropy(probability.sum(dim=-2), dims=(-1,)),
        _entropy(probability, dims=(-2, -1)),
    )


def _entropy(probability: Tensor, dims: tuple[int, ...]) -> Tensor:
    # Clamping inside the log only: p log p -> 0 at p = 0 and its gradient stays finite.
    clamped = probability.clamp_min(torch.finfo(probability.dtype).tiny)
    if torch.is_grad_enabled() and probability.requires_grad:
        return -(probability * clamped.log()).sum(dim=dims)
    return -clamped.log_().mul_(probability).sum(dim=dims)  # the same products, in place


def nmi_from_joint_histogram(counts: Tensor) -> Tensor:
    """Studholme NMI ``(H[A] + H[B]) / H[A, B]`` of joint histograms ``(..., B, K, K)``, ``(..., B)``, in ``[1, 2]``.

    Convention:
        When the joint entropy is 0 (both images fall in a single bin) the mutual information is 0 and the score
        is defined as 1, its value for independent images. Counts from several batches or processes may be summed
        before this call (streaming evaluation).

    Example:
        >>> nmi_from_joint_histogram(torch.tensor([[[1.0, 0.0], [0.0, 1.0]], [[1.0, 1.0], [1.0, 1.0]]]))
        tensor([2., 1.])
    """
    check_floating("counts", counts)
    if counts.ndim < 3 or counts.shape[-1] != counts.shape[-2]:
        raise ValueError(f"counts must have shape (B, K, K) or (..., B, K, K), got {tuple(counts.shape)}")
    return _nmi_from_entropies(*entropies(counts))


def _nmi_from_entropies(
    captured_entropy: Tensor, reference_entropy: Tensor, joint_entropy: Tensor, informative: Tensor | None = None
) -> Tensor:
    """``(H[A] + H[B]) / H[A, B]`` where ``informative`` (default: ``H[A, B] > eps``), 1 elsewhere."""
    if informative is None:
        informative = joint_entropy > torch.finfo(joint_entropy.dtype).eps
    safe_joint = torch.where(informative, joint_entropy, torch.ones_like(joint_entropy))
    return torch.where(informative, (captured_entropy + reference_entropy) / safe_joint, torch.ones_like(safe_joint))


def nmi(
    captured: Tensor,
    reference: Tensor,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    kernel: str = "hard",
    reference_kernel: str = "hard",
    valid_mask: Tensor | None = None,
) -> Tensor:
    """Normalized mutual information of each captured/reference pair, ``(B,)``.

    Args:
        captured: ``(B, 1, H, W)``, ``(B, H, W)`` or ``(B, N)``, floating point.
        reference: same shape as ``captured``, or ``(C, *captured.shape)`` to score each captured image against
            ``C`` candidates (the captured bins are computed once).
        bins: number of equal-width bins over ``value_range``.
        value_range: ``(low, high)``; values outside are clipped into the edge bins.
        kernel: ``"hard"`` (unit counts, as scikit-image; no gradient), ``"triangular"`` or ``"xu"`` (Parzen
            windows, differentiable in ``captured``).
        reference_kernel: the same choice for ``reference``.
        valid_mask: bool ``(H, W)``, ``(1, 1, H, W)`` or ``(B, 1, H, W)``; ``False`` pixels are left out.

    Returns:
        ``(H[A] + H[B]) / H[A, B]`` in ``[1, 2]``: 2 for images that determine each other, about 1 for independent
        ones; ``(B,)``, or ``(C, B)`` for candidates. Same dtype as ``captured``.

    Raises:
        MemoryBudgetError: for soft kernels whose ``(C, B, bins, bins)`` histograms and entropies would exceed the
            memory budget (see :func:`~enmi_torch.histogram.joint_histogram`); hard bins need no ``bins^2`` table.

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> nmi(image, image, bins=4)
        tensor([2.])
        >>> nmi(image, image.transpose(-1, -2), bins=4)
        tensor([1.])
    """
    check_option("kernel", kernel, ("hard", "triangular", "xu"))
    if kernel == "hard" and reference_kernel == "hard" and _few_pixels(captured, bins):
        # Same score as the hard joint histogram's, with O(pixels) logarithms per sample instead of O(bins^2).
        return _nmi_from_entropies(
            *hard_entropies(captured, reference, bins=bins, value_range=value_range, valid_mask=valid_mask)
        )
    inputs = _prepare(captured, reference, bins, value_range, None, valid_mask, kernel, reference_kernel, None)
    return nmi_from_joint_histogram(_joint_histogram(inputs, scored=True))


def _few_pixels(captured: Tensor, bins: int) -> bool:
    """Whether an image has fewer than ``bins^2 / 4`` pixels, where pixel-wise hard entropies beat the histogram.

    ``data_tools/bench_paper_simulation.py`` on CPU, 32 bins: 2.4x faster at 66 pixels, about even at 256
    (``bins^2 / 4``), 2x slower from a few thousand.
    """
    if not isinstance(captured, Tensor) or captured.ndim < 2 or isinstance(bins, bool) or not isinstance(bins, int):
        return False
    if captured.shape[0] == 0:
        return False  # the joint histogram's checks refuse an empty batch
    return 4 * captured[0].numel() < bins * bins


def enmi(
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
) -> Tensor:
    """Enhanced NMI: each captured pixel spreads its unit weight over the bins by its Gaussian likelihood, ``(B,)``.

    A captured pixel ``v`` with noise variance ``sigma^2`` (``sigma^2 = N0 / A`` for a road tile of focal-plane
    area ``A``) counts in captured bin ``i`` with the weight its likelihood gives amplitudes in that bin, paired with
    the reference pixel's bin; ENMI is the Studholme NMI of that joint histogram.

    Args:
        captured: noisy image ``(B, 1, H, W)``, ``(B, H, W)`` or ``(B, N)``, floating point.
        reference: noiseless map section, same shape; or ``(C, *captured.shape)``, ``C`` candidate sections per
            captured image, scored against likelihood weights computed once (the costly part).
        variance: per-pixel noise variance (> 0 where valid): a number, ``(H, W)``, ``(1, 1, H, W)`` or
            ``(B, 1, H, W)``.
        bins: number of equal-width bins over ``value_range``.
        value_range: ``(low, high)``.
        kernel: how a captured pixel's unit spreads over the bins (the name :func:`nmi` uses for its Parzen
            windows): ``"mass"`` (probability of each bin under ``N(v, sigma^2)``, tails in the edge bins),
            ``"density"`` (density at the bin centres, normalised over bins) or ``"truncated"`` (the masses inside the
            range, renormalised).
        log_prior: optional log prior of the amplitude per bin, ``(bins,)`` or ``(B, bins)`` (e.g.
            :func:`~enmi_torch.binning.gaussian_log_prior`): weights become the MAP posterior.
        reference_kernel: ``"hard"`` (noiseless map, default) or ``"triangular"``/``"xu"`` for a reference gradient.
        valid_mask: bool, broadcast like ``variance``; ``False`` pixels are left out.
        reliability: each pixel counts with its reliability ``s^2 / (s^2 + sigma^2)``
            (:func:`~enmi_torch.binning.reliability_weights`) instead of a unit weight, so very noisy pixels weigh
            less in the histogram; with one variance for all pixels the score is unchanged. Uses the dense
            (autograd) histogram path.

    Returns:
        ENMI in ``[1, 2]``, ``(B,)`` (``(C, B)`` for candidates), same dtype as ``captured``; it tends to hard
        :func:`nmi` as the variance tends to 0.

    Raises:
        MemoryBudgetError: when the ``(C, B, bins, bins)`` histograms and their entropies would exceed the memory
            budget (see :func:`~enmi_torch.histogram.joint_histogram`).

    Convention:
        Differentiable in ``captured`` and ``variance`` (and ``reference`` with a soft reference kernel).

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 16, 16, generator=generator) * 256
        >>> captured = reference + 8 * torch.randn(1, 1, 16, 16, generator=generator)
        >>> enmi(captured, reference, 64.0, bins=8)
        tensor([1.5003])
        >>> enmi(captured, reference.roll(1, -1), 64.0, bins=8)
        tensor([1.0179])
        >>> enmi(captured, torch.stack([reference, reference.roll(1, -1)]), 64.0, bins=8)
        tensor([[1.5003],
                [1.0179]])
    """
    check_option("kernel", kernel, LIKELIHOOD_WEIGHTS)
    check_variance_given(variance)
    if not isinstance(reliability, bool):
        raise TypeError(f"reliability must be True or False, got {reliability!r}")
    inputs = _prepare(
        captured, reference, bins, value_range, variance, valid_mask, kernel, reference_kernel, log_prior, "variance"
    )
    if reliability:
        pixel_weight = reliability_weights(inputs.captured, inputs.variance, inputs.valid)
        inputs = inputs._replace(pair_weight=pixel_weight, weighted=True)
    return nmi_from_joint_histogram(_joint_histogram(inputs, scored=True))
