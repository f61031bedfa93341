"""The mixture-likelihood score: mutual information with each captured pixel's noise integrated out.

Model: a captured pixel ``v_n`` is a true amplitude in some bin ``i``, seen through Gaussian noise of variance
``sigma_n^2``; for an amplitude uniform in bin ``i`` the density of ``v_n`` is proportional to ``L_n(i)``, the mass
``N(v_n, sigma_n^2)`` puts in bin ``i`` (:func:`~enmi_torch.binning.truncated_likelihood_weights`: tails outside the
range dropped, rows normalised). The reference (map) pixel is hard-binned, ``j_n``. The soft joint histogram

    ``J[i, j] = sum_n L_n(i) [j_n = j]``,  ``p(i | j) = J[i, j] / sum_i J[i, j]``,  ``p(i) = sum_j J[i, j] / n``

gives two mixture models of the captured pixels, one given the reference bin, one without it, and the score is their
log-likelihood ratio per valid pixel, in nats:

    ``M = (1 / n) sum_n [log sum_i L_n(i) p(i | j_n) - log sum_i L_n(i) p(i)]``.

A pixel whose likelihood is flat over the bins adds ``log(1 / K) - log(1 / K) = 0`` of its own instead of a full unit
of histogram weight (its ``1 / K`` per bin still enters ``J``: the other pixels' ``p(i | j)`` and ``p(i)`` move by
``O(1 / n)``), and as ``sigma -> 0`` (``L_n`` one-hot) ``M`` is the plug-in mutual information
``H[A] + H[B] - H[A, B]`` of the hard joint histogram.

``em_steps`` deconvolve the noise: each step replaces each model's bin probabilities by the mean responsibilities of
its pixels, ``r_n(i) ∝ L_n(i) p(i | j_n)`` (so ``J[i, j] = sum_n r_n(i) [j_n = j]``) for the conditional model and
``r_n(i) ∝ L_n(i) p(i)`` for the marginal one. Each step is an EM step of that model's likelihood, which never
decreases; both models are fitted alike so that the ratio compares two fits of equal effort.

Convention:
    Captured values are weighted over ``bins`` equal bins of ``value_range``, truncated to it (a value far above the
    range counts in the top bin); reference values are hard-binned, clipped into the edge bins. The score is not a
    sum over batches: the per-pixel terms need the whole joint histogram first.
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from enmi_torch._checks import (
    check_bins,
    check_floating,
    check_non_negative_int,
    check_positive_int,
    check_value_range,
)
from enmi_torch.binning import hard_bin_index, truncated_likelihood_weights
from enmi_torch.correlation_ratio import default_model_variance
from enmi_torch.histogram import _prepare
from enmi_torch.score_surface import Surface, _check_inputs, _ecr_surface

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
        captured: noisy image ``(B, 1, H, W)``, ``(B, H, W)`` or ``(B, N)``, floating point.
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
    if variance is None:
        raise ValueError("variance must be a number or a tensor of per-pixel variances, got None")
    check_floating("captured", captured)
    em_steps = check_non_negative_int("em_steps", em_steps)
    inputs = _prepare(captured, reference, bins, value_range, variance, valid_mask, "mass", "hard", None, "variance")
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
    local: Tensor,
    window: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    em_steps: int = 0,
    local_mask: Tensor | None = None,
    window_mask: Tensor | None = None,
    candidates: int = 8,
    max_candidates: int = 64,
) -> Surface:
    """:func:`mixture_information` of ``local`` at the promising placements inside ``window``, in two stages.

    A cheap full surface, :func:`~enmi_torch.score_surface.ecr_surface` with the same variance (FFT-fast), picks the
    ``candidates`` highest separated peaks (local maxima of their 3 x 3 neighbourhood); each peak and its 8
    neighbours are rescored exactly. While the exact best lies in the lower half of the rescored peaks' cheap ranking
    (or next to such a peak), the cheap ranking is not trusted that far: the number of peaks doubles (the new ones
    rescored), up to ``max_candidates`` or every peak.

    Args:
        local: noisy local image ``(B, 1, h, w)``, floating point.
        window: noiseless map section ``(1 or B, 1, Hw, Ww)`` holding every placement, ``Hw >= h``, ``Ww >= w``.
        variance: per-pixel noise variance of ``local`` (> 0 where valid): a number, ``(h, w)``, ``(1, 1, h, w)``
            or ``(B, 1, h, w)``.
        bins: number of equal-width bins over ``value_range``.
        value_range: ``(low, high)``.
        em_steps: as in :func:`mixture_information`.
        local_mask: bool, broadcast like ``variance``; ``False`` pixels are left out.
        window_mask: bool ``(Hw, Ww)``, ``(1, 1, Hw, Ww)`` or one per window; ``False`` cells are left out.
        candidates: peaks of the cheap surface rescored first, >= 1.
        max_candidates: at most this many peaks rescored, >= ``candidates``.

    Returns:
        :class:`~enmi_torch.score_surface.Surface` ``(B, Hw - h + 1, Ww - w + 1)``: ``score[b, u, v]`` equals
        ``mixture_information(local[b], window[b, :, u:u + h, v:v + w], variance, valid_mask=...)`` where rescored
        (0 where nothing overlaps) and is ``-inf`` elsewhere, so that the surface keeps its shape and its argmax;
        ``overlap`` is given everywhere.

    Convention:
        As :mod:`~enmi_torch.score_surface`: ``[b, u, v]`` places the local image's top-left pixel on window cell
        ``(u, v)`` (row, column); no gradient; float64 for float64 inputs, float32 otherwise.

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> window = torch.rand(1, 1, 12, 12, generator=generator) * 256
        >>> local = window[..., 3:9, 2:8] + 4 * torch.randn(1, 1, 6, 6, generator=generator)
        >>> surface = mixture_surface(local, window, 16.0, bins=8)
        >>> surface.score.shape, divmod(int(surface.score.flatten().argmax()), 7)
        (torch.Size([1, 7, 7]), (3, 2))
    """
    if variance is None:
        raise ValueError("variance must be a number or a tensor of per-pixel variances, got None")
    bins = check_bins(bins)
    value_range = check_value_range(value_range)
    em_steps = check_non_negative_int("em_steps", em_steps)
    candidates = check_positive_int("candidates", candidates)
    max_candidates = check_positive_int("max_candidates", max_candidates)
    if max_candidates < candidates:
        raise ValueError(f"max_candidates must be >= candidates ({candidates}), got {max_candidates}")
    inputs = _check_inputs(local, window, local_mask, window_mask, value_range, variance, bins)
    with torch.no_grad():
        cheap = _ecr_surface(inputs, default_model_variance(bins, value_range), bins, value_range)
        batch, height, width = inputs.local.shape
        weights = truncated_likelihood_weights(
            inputs.local.reshape(batch, -1), inputs.variance.reshape(batch, -1), bins, value_range
        )
        window_bins = hard_bin_index(inputs.window, bins, value_range)
        scores = []
        for sample in range(batch):
            window_index = sample if inputs.window.shape[0] > 1 else 0
            exact = functools.partial(
                _placement_scores,
                weights=weights[sample : sample + 1],
                section_bins=window_bins[window_index].unfold(0, height, 1).unfold(1, width, 1),
                section_valid=inputs.window_valid[window_index].unfold(0, height, 1).unfold(1, width, 1),
                local_valid=inputs.local_valid[sample],
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
    local_valid: Tensor,
    bins: int,
    em_steps: int,
) -> Tensor:
    """Exact scores ``(P,)`` of one local image at placements ``(P, 2)`` (row, column).

    ``weights`` ``(1, N, K)``; ``section_bins`` and ``section_valid`` ``(rows, cols, h, w)``, the window's reference
    bins and valid cells under each placement; ``local_valid`` ``(h, w)``.
    """
    rows, cols = placements.unbind(-1)
    reference_bins = section_bins[rows, cols].reshape(placements.shape[0], 1, -1)
    valid = (section_valid[rows, cols] & local_valid).reshape(placements.shape[0], 1, -1)
    return _mixture_score(weights, reference_bins, valid.to(weights.dtype), bins, em_steps)[:, 0]


def _rescore_peaks(cheap: Tensor, exact, candidates: int, max_candidates: int) -> Tensor:
    """``(rows, cols)`` exact scores around the best peaks of ``cheap`` ``(rows, cols)``, ``-inf`` elsewhere.

    ``exact`` maps placements ``(P, 2)`` (row, column) to scores ``(P,)``. Peaks are ranked by cheap score; each
    rescored placement belongs to the best-ranked peak it neighbours. The number of peaks doubles while the exact
    best belongs to a peak in the lower half of those rescored (up to ``max_candidates`` or every peak).
    """
    rows, cols = cheap.shape
    pooled = torch.nn.functional.max_pool2d(cheap[None, None], 3, stride=1, padding=1)[0, 0]
    peaks = (cheap >= pooled).flatten().nonzero()[:, 0]
    peaks = peaks[cheap.flatten()[peaks].argsort(descending=True, stable=True)]
    limit = min(max_candidates, peaks.numel())
    offsets = torch.stack(torch.meshgrid(torch.arange(-1, 2), torch.arange(-1, 2), indexing="ij"), -1).reshape(9, 2)
    offsets = offsets.to(cheap.device)
    owner = torch.full((rows * cols,), limit, dtype=torch.long, device=cheap.device)
    score = torch.full((rows * cols,), -torch.inf, dtype=cheap.dtype, device=cheap.device)
    rescored = torch.zeros(rows * cols, dtype=torch.bool, device=cheap.device)
    done, count = 0, min(candidates, limit)
    while True:
        centres = torch.stack([peaks[done:count] // cols, peaks[done:count] % cols], -1)
        around = (centres.unsqueeze(1) + offsets).reshape(-1, 2)
        inside = (around[:, 0] >= 0) & (around[:, 0] < rows) & (around[:, 1] >= 0) & (around[:, 1] < cols)
        ranks = torch.arange(done, count, device=cheap.device).repeat_interleave(9)[inside]
        owner.scatter_reduce_(0, around[inside, 0] * cols + around[inside, 1], ranks, "amin")
        new = ((owner < count) & ~rescored).nonzero()[:, 0]
        score[new] = exact(torch.stack([new // cols, new % cols], -1))
        rescored[new] = True
        best = int(score.argmax())
        if 2 * int(owner[best]) < count or count >= limit:
            return score.view(rows, cols)
        done, count = count, min(2 * count, limit)


def direct_mixture_surface(
    local: Tensor,
    window: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    em_steps: int = 0,
    local_mask: Tensor | None = None,
    window_mask: Tensor | None = None,
) -> Surface:
    """The reference for :func:`mixture_surface`: one :func:`mixture_information` per placement, every placement.

    Slow; use it on small windows. Arguments and result as :func:`mixture_surface`, with every entry rescored.

    Example:
        >>> window = torch.arange(64.0).reshape(1, 1, 8, 8) * 4 + 2
        >>> surface = direct_mixture_surface(window[..., 2:6, 1:5], window, 1e-6, bins=64)
        >>> round(surface.score[0, 2, 1].item(), 4)  # log 16: 16 pixels, each its own bin
        2.7726
    """
    if variance is None:
        raise ValueError("variance must be a number or a tensor of per-pixel variances, got None")
    bins = check_bins(bins)
    value_range = check_value_range(value_range)
    em_steps = check_non_negative_int("em_steps", em_steps)
    inputs = _check_inputs(local, window, local_mask, window_mask, value_range, variance, bins)
    batch, height, width = inputs.local.shape
    rows = inputs.window.shape[1] - height + 1
    cols = inputs.window.shape[2] - width + 1
    score = inputs.local.new_empty(batch, rows, cols)
    overlap = inputs.local.new_empty(batch, rows, cols)
    with torch.no_grad():
        for sample in range(batch):
            window_index = sample if inputs.window.shape[0] > 1 else 0
            for row in range(rows):
                for col in range(cols):
                    section = inputs.window[window_index, row : row + height, col : col + width]
                    valid = (
                        inputs.local_valid[sample]
                        & inputs.window_valid[window_index, row : row + height, col : col + width]
                    )
                    overlap[sample, row, col] = int(valid.sum())
                    score[sample, row, col] = (
                        0.0
                        if not valid.any()
                        else mixture_information(
                            inputs.local[sample][None, None],
                            section[None, None],
                            inputs.variance[sample][None, None],
                            bins=bins,
                            value_range=value_range,
                            em_steps=em_steps,
                            valid_mask=valid[None, None],
                        )[0]
                    )
    return Surface(score, overlap)
