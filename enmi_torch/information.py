"""Entropies and the normalized mutual information (Studholme) of joint histograms: what ENMI and NMI share.

The scores that build joint histograms (:mod:`~enmi_torch.scores.enmi`, :mod:`~enmi_torch.scores.nmi`) turn their
counts into a score here; counts summed over batches or processes give the same score (streaming evaluation).
"""

from __future__ import annotations

import torch
from torch import Tensor

from enmi_torch.utils.checks import check_counts, check_floating


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
    check_counts("counts", counts)
    return nmi_from_entropies(*entropies(counts))


def nmi_from_entropies(
    captured_entropy: Tensor, reference_entropy: Tensor, joint_entropy: Tensor, informative: Tensor | None = None
) -> Tensor:
    """Studholme NMI ``(H[A] + H[B]) / H[A, B]`` from the three entropies, where ``informative``, and 1 elsewhere.

    For scores that compute the entropies themselves (hard entropies at the pixels, FFT surfaces);
    ``informative`` defaults to ``H[A, B] > eps`` (a zero joint entropy scores 1, as for independent images).

    Example:
        >>> nmi_from_entropies(torch.tensor([0.6931]), torch.tensor([0.6931]), torch.tensor([0.6931]))
        tensor([2.])
    """
    if informative is None:
        informative = joint_entropy > torch.finfo(joint_entropy.dtype).eps
    safe_joint = torch.where(informative, joint_entropy, torch.ones_like(joint_entropy))
    return torch.where(informative, (captured_entropy + reference_entropy) / safe_joint, torch.ones_like(safe_joint))
