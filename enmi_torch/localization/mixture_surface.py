"""The mixture-likelihood score (:mod:`enmi_torch.mixture`) over all placements: a cheap surface's peaks rescored."""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from enmi_torch._checks import (
    check_bins,
    check_non_negative_int,
    check_positive_int,
    check_value_range,
    check_variance_given,
)
from enmi_torch.binning import hard_bin_index, truncated_likelihood_weights
from enmi_torch.correlation_ratio import default_model_variance
from enmi_torch.localization.surface import Surface, _check_inputs, _ecr_surface
from enmi_torch.mixture import _mixture_score, mixture_information


def mixture_surface(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    em_steps: int = 0,
    captured_mask: Tensor | None = None,
    reference_mask: Tensor | None = None,
    candidates: int = 8,
    max_candidates: int = 64,
) -> Surface:
    """:func:`mixture_information` of ``captured`` at the promising placements inside ``reference``, in two stages.

    A cheap full surface, :func:`~enmi_torch.localization.surface.ecr_surface` with the same variance (FFT-fast),
    picks the ``candidates`` highest separated peaks (captured maxima of their 3 x 3 neighbourhood); each peak and its 8
    neighbours are rescored exactly. While the exact best lies in the lower half of the rescored peaks' cheap ranking
    (or next to such a peak), the cheap ranking is not trusted that far: the number of peaks doubles (the new ones
    rescored), up to ``max_candidates`` or every peak.

    Args:
        captured: noisy captured image ``(B, 1, h, w)``, floating point.
        reference: noiseless map section ``(1 or B, 1, Hw, Ww)`` holding every placement, ``Hw >= h``, ``Ww >= w``.
        variance: per-pixel noise variance of ``captured`` (> 0 where valid): a number, ``(h, w)``, ``(1, 1, h, w)``
            or ``(B, 1, h, w)``.
        bins: number of equal-width bins over ``value_range``.
        value_range: ``(low, high)``.
        em_steps: as in :func:`mixture_information`.
        captured_mask: bool, broadcast like ``variance``; ``False`` pixels are left out.
        reference_mask: bool ``(Hw, Ww)``, ``(1, 1, Hw, Ww)`` or one per reference; ``False`` cells are left out.
        candidates: peaks of the cheap surface rescored first, >= 1.
        max_candidates: at most this many peaks rescored, >= ``candidates``.

    Returns:
        :class:`~enmi_torch.localization.surface.Surface` ``(B, Hw - h + 1, Ww - w + 1)``: ``score[b, u, v]`` equals
        ``mixture_information(captured[b], reference[b, :, u:u + h, v:v + w], variance, valid_mask=...)`` where rescored
        (0 where nothing overlaps) and is ``-inf`` elsewhere, so that the surface keeps its shape and its argmax;
        ``overlap`` is given everywhere.

    Convention:
        As :mod:`~enmi_torch.localization.surface`: ``[b, u, v]`` places the captured image's top-left pixel on
        reference cell ``(u, v)`` (row, column); no gradient; float64 for float64 inputs, float32 otherwise.

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 12, 12, generator=generator) * 256
        >>> captured = reference[..., 3:9, 2:8] + 4 * torch.randn(1, 1, 6, 6, generator=generator)
        >>> surface = mixture_surface(captured, reference, 16.0, bins=8)
        >>> surface.score.shape, divmod(int(surface.score.flatten().argmax()), 7)
        (torch.Size([1, 7, 7]), (3, 2))
    """
    check_variance_given(variance)
    bins = check_bins(bins)
    value_range = check_value_range(value_range)
    em_steps = check_non_negative_int("em_steps", em_steps)
    candidates = check_positive_int("candidates", candidates)
    max_candidates = check_positive_int("max_candidates", max_candidates)
    if max_candidates < candidates:
        raise ValueError(f"max_candidates must be >= candidates ({candidates}), got {max_candidates}")
    inputs = _check_inputs(captured, reference, captured_mask, reference_mask, value_range, variance, bins)
    with torch.no_grad():
        cheap = _ecr_surface(inputs, default_model_variance(bins, value_range), bins, value_range)
        batch, height, width = inputs.captured.shape
        weights = truncated_likelihood_weights(
            inputs.captured.reshape(batch, -1), inputs.variance.reshape(batch, -1), bins, value_range
        )
        window_bins = hard_bin_index(inputs.reference, bins, value_range)
        scores = []
        for sample in range(batch):
            window_index = sample if inputs.reference.shape[0] > 1 else 0
            exact = functools.partial(
                _placement_scores,
                weights=weights[sample : sample + 1],
                section_bins=window_bins[window_index].unfold(0, height, 1).unfold(1, width, 1),
                section_valid=inputs.reference_valid[window_index].unfold(0, height, 1).unfold(1, width, 1),
                captured_valid=inputs.captured_valid[sample],
                bins=bins,
                em_steps=em_steps,
            )
            scores.append(_rescore_peaks(cheap.score[sample], exact, candidates, max_candidates))
        return Surface(torch.stack(scores), cheap.overlap)


def _placement_scores(
    placements: Tensor,
    *,
    weights: Tensor,
    section_bins: Tensor,
    section_valid: Tensor,
    captured_valid: Tensor,
    bins: int,
    em_steps: int,
) -> Tensor:
    """Exact scores ``(P,)`` of one captured image at placements ``(P, 2)`` (row, column).

    ``weights`` ``(1, N, K)``; ``section_bins`` and ``section_valid`` ``(rows, cols, h, w)``, the reference's reference
    bins and valid cells under each placement; ``captured_valid`` ``(h, w)``.
    """
    rows, cols = placements.unbind(-1)
    reference_bins = section_bins[rows, cols].reshape(placements.shape[0], 1, -1)
    valid = (section_valid[rows, cols] & captured_valid).reshape(placements.shape[0], 1, -1)
    return _mixture_score(weights, reference_bins, valid.to(weights.dtype), bins, em_steps)[:, 0]


def _rescore_peaks(
    cheap: Tensor, exact, candidates: int, max_candidates: int, *, complete_best: bool = False
) -> Tensor:
    """Exact scores around the best peaks of ``cheap`` (``(rows, cols)`` or ``(yaws, rows, cols)``), ``-inf`` elsewhere.

    ``exact`` maps placements ``(P, cheap.ndim)`` (indices) to scores ``(P,)``. Peaks are the finite maxima of their
    3 x 3 (x 3) neighbourhood, ranked by cheap score; each rescored placement belongs to the best-ranked peak it
    neighbours. The number of peaks doubles while the exact best belongs to a peak in the lower half of those rescored
    (up to ``max_candidates`` or every peak). With ``complete_best`` the exact best's own neighbourhood is then
    rescored too (and again while the best moves), for the sub-cell fit around it.
    """
    shape, device = cheap.shape, cheap.device
    pooled = cheap
    for axis in range(cheap.ndim):  # separable 3 x 3 (x 3) maximum: max_pool3d is slow on the CPU
        padded = torch.nn.functional.pad(pooled.movedim(axis, -1), (1, 1), value=-torch.inf)
        pooled = torch.maximum(torch.maximum(padded[..., :-2], padded[..., 1:-1]), padded[..., 2:]).movedim(-1, axis)
    peaks = ((cheap >= pooled) & torch.isfinite(cheap)).flatten().nonzero()[:, 0]
    peaks = peaks[cheap.flatten()[peaks].argsort(descending=True, stable=True)]
    limit = min(max_candidates, peaks.numel())
    offsets = torch.cartesian_prod(*[torch.arange(-1, 2, device=device)] * cheap.ndim).reshape(-1, cheap.ndim)
    sizes = torch.tensor(shape, device=device)
    strides = torch.tensor(torch.empty(shape, device="meta").stride(), device=device)
    owner = torch.full((cheap.numel(),), limit, dtype=torch.long, device=device)
    score = torch.full((cheap.numel(),), -torch.inf, dtype=cheap.dtype, device=device)
    rescored = torch.zeros(cheap.numel(), dtype=torch.bool, device=device)

    def unravel(flat: Tensor) -> Tensor:
        return torch.stack([flat // stride % size for stride, size in zip(strides, sizes, strict=True)], -1)

    def neighbours(flat: Tensor) -> tuple[Tensor, Tensor]:
        """Flat indices of the in-range neighbours of ``flat`` ``(n,)`` and whose neighbour each is."""
        around = unravel(flat).unsqueeze(1) + offsets
        inside = ((around >= 0) & (around < sizes)).all(-1)
        source = torch.arange(flat.numel(), device=device).unsqueeze(1).expand_as(inside)
        return (around[inside] * strides).sum(-1), source[inside]

    def rescore(flat: Tensor) -> None:
        score[flat] = exact(unravel(flat))
        rescored[flat] = True

    if limit == 0:
        return score.view(shape)
    done, count = 0, min(candidates, limit)
    while True:
        around, source = neighbours(peaks[done:count])
        owner.scatter_reduce_(0, around, source + done, "amin")
        rescore(((owner < count) & ~rescored).nonzero()[:, 0])
        best = int(score.argmax())
        if 2 * int(owner[best]) < count or count >= limit:
            break
        done, count = count, min(2 * count, limit)
    while complete_best:
        around = neighbours(score.argmax().reshape(1))[0]
        missing = around[~rescored[around]]
        if missing.numel() == 0:
            break
        rescore(missing)
    return score.view(shape)


def direct_mixture_surface(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    em_steps: int = 0,
    captured_mask: Tensor | None = None,
    reference_mask: Tensor | None = None,
) -> Surface:
    """The reference for :func:`mixture_surface`: one :func:`mixture_information` per placement, every placement.

    Slow; use it on small windows. Arguments and result as :func:`mixture_surface`, with every entry rescored.

    Example:
        >>> reference = torch.arange(64.0).reshape(1, 1, 8, 8) * 4 + 2
        >>> surface = direct_mixture_surface(reference[..., 2:6, 1:5], reference, 1e-6, bins=64)
        >>> round(surface.score[0, 2, 1].item(), 4)  # log 16: 16 pixels, each its own bin
        2.7726
    """
    check_variance_given(variance)
    bins = check_bins(bins)
    value_range = check_value_range(value_range)
    em_steps = check_non_negative_int("em_steps", em_steps)
    inputs = _check_inputs(captured, reference, captured_mask, reference_mask, value_range, variance, bins)
    batch, height, width = inputs.captured.shape
    rows = inputs.reference.shape[1] - height + 1
    cols = inputs.reference.shape[2] - width + 1
    score = inputs.captured.new_empty(batch, rows, cols)
    overlap = inputs.captured.new_empty(batch, rows, cols)
    with torch.no_grad():
        for sample in range(batch):
            window_index = sample if inputs.reference.shape[0] > 1 else 0
            for row in range(rows):
                for col in range(cols):
                    section = inputs.reference[window_index, row : row + height, col : col + width]
                    valid = (
                        inputs.captured_valid[sample]
                        & inputs.reference_valid[window_index, row : row + height, col : col + width]
                    )
                    overlap[sample, row, col] = int(valid.sum())
                    score[sample, row, col] = (
                        0.0
                        if not valid.any()
                        else mixture_information(
                            inputs.captured[sample][None, None],
                            section[None, None],
                            inputs.variance[sample][None, None],
                            bins=bins,
                            value_range=value_range,
                            em_steps=em_steps,
                            valid_mask=valid[None, None],
                        )[0]
                    )
    return Surface(score, overlap)
