"""The mixture-likelihood score: mutual information with each captured pixel's noise integrated out.

Model (:ref:`model-mixture`): ENMI's soft joint histogram gives two mixture models of the captured pixels, one given
the reference bin and one without it; the score ``M`` is their log-likelihood ratio per valid pixel, in nats, and
``em_steps`` fit both models' bin probabilities to the noisy pixels by expectation-maximisation.

A captured pixel is a true amplitude in some bin seen through Gaussian noise of variance ``sigma_n^2``; its
likelihood of each bin is the mass ``N(v_n, sigma_n^2)`` puts there
(:func:`~enmi_torch.binning.truncated_likelihood_weights`: tails outside the range dropped, rows normalised); the
reference (map) pixel is hard-binned. A pixel whose likelihood is flat over the bins adds nothing of its own instead
of a full unit of histogram weight, and as ``sigma -> 0`` ``M`` is the plug-in mutual information
``H[A] + H[B] - H[A, B]`` of the hard joint histogram. Each EM step never decreases its model's likelihood; both
models are fitted alike so that the ratio compares two fits of equal effort.

Convention:
    Captured values are weighted over ``bins`` equal bins of ``value_range``, truncated to it (a value far above the
    range counts in the top bin); reference values are hard-binned, clipped into the edge bins. The score is not a
    sum over batches: the per-pixel terms need the whole joint histogram first.

Over every placement, :func:`mixture_surface` ranks the placements by the ECR surface with the same variance
(FFT-fast) and scores the neighbourhoods of its best peaks exactly (:func:`~enmi_torch.placement.peaks.rescore_peaks`).
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from enmi_torch.binning import hard_bin_index, truncated_likelihood_weights
from enmi_torch.histogram import prepare_inputs
from enmi_torch.placement.inputs import Surface, check_inputs
from enmi_torch.placement.peaks import rescore_peaks
from enmi_torch.scores.base import Score, reduce_loss
from enmi_torch.scores.ecr_model_variance import default_model_variance
from enmi_torch.scores.ecr_placements import ecr_surface_from_inputs
from enmi_torch.utils.budget import check_histogram_memory, check_surface_memory
from enmi_torch.utils.checks import (
    check_bins,
    check_floating,
    check_non_negative_int,
    check_positive_int,
    check_value_range,
    check_variance_given,
)

# Candidates per chunk are chosen so one chunk's (C, B, N, bins) per-pixel tensors stay near this many elements.
_CHUNK_ELEMENTS = 1 << 21


def mixture_information(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    em_steps: int = 0,
    valid_mask: Tensor | None = None,
) -> Tensor:
    """Mixture-likelihood mutual information: the noise-aware log-likelihood ratio per valid pixel, nats, ``(B,)``.

    Args:
        captured: noisy image ``(B, 1, H, W)`` or ``(B, H, W)`` (flat samples: ``(B, 1, N)``), floating point.
        reference: noiseless map section, same shape; or ``(C, *captured.shape)``, ``C`` candidates per image (the
            captured likelihoods are computed once).
        variance: per-pixel noise variance of ``captured`` (> 0 where valid): a number, ``(H, W)``,
            ``(1, 1, H, W)`` or ``(B, 1, H, W)``.
        bins: number of equal-width bins over ``value_range``, for both images.
        value_range: ``(low, high)`` of the bins.
        em_steps: EM steps fitting the bin probabilities of both models to the noisy pixels (see the module
            docstring); 0 scores the plug-in soft histogram.
        valid_mask: bool, broadcast like ``variance``; ``False`` pixels are left out (they may hold NaN).

    Returns:
        ``M`` ``(B,)`` (``(C, B)`` for candidates), same dtype as ``captured``: the plug-in mutual information of
        the hard histogram in the noiseless limit, with noisy pixels counting by how much their likelihood tells
        the bins apart.

    Convention:
        Differentiable in ``captured`` and ``variance`` (the reference is hard-binned).

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 16, 16, generator=generator) * 256
        >>> captured = reference + 8 * torch.randn(1, 1, 16, 16, generator=generator)
        >>> mixture_information(captured, torch.stack([reference, reference.roll(1, -1)]), 64.0, bins=8)
        tensor([[1.5302],
                [0.0894]])
    """
    check_variance_given(variance)
    check_floating("captured", captured)
    em_steps = check_non_negative_int("em_steps", em_steps)
    inputs = prepare_inputs(
        captured, reference, bins, value_range, variance, valid_mask, "mass", "hard", None, "variance"
    )
    # The (C * B * bins, bins) histograms, their conditional probabilities and products, and (B, N, bins) weights.
    candidates = inputs.reference.shape[0] if inputs.with_candidates else None
    check_histogram_memory(
        inputs.captured, inputs.bins, candidates, captured_planes=True, reference_planes=False, scored=True
    )
    weights = truncated_likelihood_weights(inputs.captured, inputs.variance, inputs.bins, inputs.value_range)
    reference_bins = hard_bin_index(inputs.reference, inputs.bins, inputs.value_range)
    score = _mixture_score(weights, reference_bins, inputs.pair_weight, inputs.bins, em_steps)
    return (score if inputs.with_candidates else score[0]).to(inputs.out_dtype)


def _mixture_score(weights: Tensor, reference_bins: Tensor, valid: Tensor | None, bins: int, em_steps: int) -> Tensor:
    """``M`` ``(C, B)`` from captured weights ``(B, N, K)`` and reference bins ``(C, B, N)``, in candidate chunks.

    ``valid`` is float 0/1, ``(B, N)`` (shared by the candidates), ``(C, B, N)`` (one mask per candidate) or
    ``None``. A candidate without any valid pixel scores 0.
    """
    candidates, batch, pixels = reference_bins.shape
    step = max(1, _CHUNK_ELEMENTS // (batch * pixels * bins))
    scores = []
    for start in range(0, candidates, step):
        part = slice(start, start + step)
        chunk_valid = None if valid is None else (valid if valid.ndim == 2 else valid[part])
        conditional, marginal, count = _mixture_log_likelihoods(
            weights, reference_bins[part], chunk_valid, bins, em_steps
        )
        scores.append(torch.where(count > 0.5, (conditional - marginal) / count.clamp_min(1), 0.0))
    return torch.cat(scores)


def _mixture_log_likelihoods(
    weights: Tensor, reference_bins: Tensor, valid: Tensor | None, bins: int, em_steps: int
) -> tuple[Tensor, Tensor, Tensor]:
    """Summed log-likelihoods of the conditional and the marginal mixture models, and the valid pixels, ``(C, B)``.

    ``weights`` ``(B, N, K)``, rows summing to 1; ``reference_bins`` ``(C, B, N)`` int64; ``valid`` as in
    :func:`_mixture_score`. The log-likelihoods leave out the per-pixel factor that turns ``L_n`` into a density.
    """
    candidates, batch, _ = reference_bins.shape
    valid_pixel = (
        torch.ones_like(reference_bins, dtype=torch.bool) if valid is None else valid.expand_as(reference_bins) > 0
    )
    count = valid_pixel.sum(-1).to(weights.dtype).unsqueeze(-1)
    spare_row = candidates * batch * bins
    offsets = torch.arange(candidates * batch, device=weights.device).view(candidates, batch, 1) * bins
    # Row (c, b, j) of the transposed histogram holds J[:, j] of candidate c and sample b; masked pixels go to a spare
    # last row that nothing reads.
    rows = torch.where(valid_pixel, reference_bins + offsets, spare_row)
    columns = (reference_bins + torch.arange(candidates, device=weights.device).view(-1, 1, 1) * bins).permute(1, 2, 0)
    transposed = _add_rows(weights, rows, spare_row + 1)
    marginal_probability = transposed[:-1].view(candidates, batch, bins, bins).sum(-2) / count.clamp_min(1)
    for step in range(em_steps + 1):
        # Each reference bin's column sum is its number of valid pixels, also after an EM step.
        conditional_probability = transposed / transposed.sum(-1, keepdim=True).clamp_min(1)
        # sum_i L_n(i) p(i | j) for every pixel, candidate and bin j in one product, then each pixel's own j_n.
        stacked = conditional_probability[:-1].view(candidates, batch, bins, bins).permute(1, 3, 0, 2)
        every_bin = weights @ stacked.reshape(batch, bins, candidates * bins)
        conditional = every_bin.gather(-1, columns).permute(2, 0, 1)
        marginal = (weights @ marginal_probability.permute(1, 2, 0)).permute(2, 0, 1)
        if step == em_steps:
            break
        # sum_n r_n(i) [j_n = j] with r_n(i) = L_n(i) p(i | j) / conditional_n is p(i | j) sum_n L_n(i) / conditional_n.
        transposed = conditional_probability * _add_rows(weights, rows, spare_row + 1, valid_pixel / _safe(conditional))
        inverse = (valid_pixel / _safe(marginal)).transpose(0, 1)
        marginal_probability = marginal_probability * (inverse @ weights).transpose(0, 1) / count.clamp_min(1)
    conditional = torch.where(valid_pixel, _safe(conditional).log(), 0.0).sum(-1)
    marginal = torch.where(valid_pixel, _safe(marginal).log(), 0.0).sum(-1)
    return conditional, marginal, count.squeeze(-1)


def _add_rows(weights: Tensor, rows: Tensor, row_count: int, scale: Tensor | None = None) -> Tensor:
    """``(row_count, K)``: pixel weights ``(B, N, K)``, times ``scale`` ``(C, B, N)``, added into ``rows``.

    ``rows`` is ``(C, B, N)``. One ``index_add_`` per candidate from the shared weights: no ``(C, B, N, K)`` copy
    where ``scale`` is ``None``.
    """
    bins = weights.shape[-1]
    result = weights.new_zeros(row_count, bins)
    for candidate, candidate_rows in enumerate(rows):
        source = weights if scale is None else weights * scale[candidate].unsqueeze(-1)
        result.index_add_(0, candidate_rows.flatten(), source.reshape(-1, bins))
    return result


def _safe(probability: Tensor) -> Tensor:
    """Per-pixel mixture probabilities of masked pixels can be 0: keep their log and reciprocal finite."""
    return probability.clamp_min(torch.finfo(probability.dtype).tiny)


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

    A cheap full surface, :func:`~enmi_torch.scores.ecr.ecr_surface` with the same variance (FFT-fast),
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
        :class:`~enmi_torch.placement.Surface` ``(B, Hw - h + 1, Ww - w + 1)``: ``score[b, u, v]`` equals
        ``mixture_information(captured[b], reference[b, :, u:u + h, v:v + w], variance, valid_mask=...)`` where rescored
        (0 where nothing overlaps) and is ``-inf`` elsewhere, so that the surface keeps its shape and its argmax;
        ``scored`` says which placements were rescored; ``overlap`` is given everywhere.

    Convention:
        As :mod:`~enmi_torch.placement.inputs`: ``[b, u, v]`` places the captured image's top-left pixel on
        reference cell ``(u, v)`` (row, column); no gradient; float64 for float64 inputs, float32 otherwise.

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 12, 12, generator=generator) * 256
        >>> captured = reference[..., 3:9, 2:8] + 4 * torch.randn(1, 1, 6, 6, generator=generator)
        >>> surface = mixture_surface(captured, reference, 16.0, bins=8)
        >>> surface.score.shape, divmod(int(surface.score.flatten().argmax()), 7), int(surface.scored.sum())
        (torch.Size([1, 7, 7]), (3, 2), 35)
    """
    check_variance_given(variance)
    bins = check_bins(bins)
    value_range = check_value_range(value_range)
    em_steps = check_non_negative_int("em_steps", em_steps)
    candidates = check_positive_int("candidates", candidates)
    max_candidates = check_positive_int("max_candidates", max_candidates)
    if max_candidates < candidates:
        raise ValueError(f"max_candidates must be >= candidates ({candidates}), got {max_candidates}")
    inputs = check_inputs(captured, reference, captured_mask, reference_mask, value_range, variance, bins)
    check_surface_memory(inputs.captured, inputs.reference, bins)
    # Each placement is rescored alone: one (bins, bins) histogram at a time, from (B, N, bins) weights.
    check_histogram_memory(
        inputs.captured.flatten(1), bins, None, captured_planes=True, reference_planes=False, scored=True
    )
    with torch.no_grad():
        cheap = ecr_surface_from_inputs(inputs, default_model_variance(bins, value_range), bins, value_range)
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
            scores.append(rescore_peaks(cheap.score[sample], exact, candidates, max_candidates))
        scores = torch.stack(scores)
        return Surface(scores, cheap.overlap, torch.isfinite(scores))


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


def mixture_loss(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    valid_mask: Tensor | None = None,
    reduction: str = "mean",
    **options,
) -> Tensor:
    """``-mixture_information(captured, reference, variance, **options)`` reduced: ``Mixture(**options).loss(...)``.

    ``reduction``: ``"none"`` (``(B,)``), ``"mean"`` or ``"sum"``; ``options``: those of :class:`Mixture`.

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> round(mixture_loss(image, image, 1.0, bins=4).item(), 4)
        -1.3863
    """
    return Mixture(**options).loss(captured, reference, variance, valid_mask=valid_mask, reduction=reduction)


class Mixture(Score):
    """The mixture score as an object: :func:`mixture_information`, :func:`mixture_surface`, :func:`mixture_loss`.

    Args:
        bins: number of equal-width bins over ``value_range``, for both images.
        value_range: ``(low, high)`` of the bins.
        em_steps: EM steps fitting the bin probabilities (see :func:`mixture_information`).

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> round(Mixture(bins=4)(image, image, 1.0).item(), 4)
        1.3863
    """

    name = "mixture"
    uses_variance = True
    _bins_captured = True

    def __init__(self, *, bins: int = 32, value_range: tuple[float, float] = (0.0, 256.0), em_steps: int = 0) -> None:
        bins = check_bins(bins)
        value_range = check_value_range(value_range)
        em_steps = check_non_negative_int("em_steps", em_steps)
        super().__init__(bins=bins, value_range=value_range, em_steps=em_steps)

    def _value(self, captured, reference, variance, valid_mask) -> Tensor:
        return mixture_information(captured, reference, variance, valid_mask=valid_mask, **self._options)

    def _surface(self, captured, reference, variance, captured_mask, reference_mask) -> Surface:
        masks = {"captured_mask": captured_mask, "reference_mask": reference_mask}
        return mixture_surface(captured, reference, variance, **masks, **self._options)

    def _loss(self, captured, reference, variance, valid_mask, reduction) -> Tensor:
        return reduce_loss(-self._value(captured, reference, variance, valid_mask), reduction)
