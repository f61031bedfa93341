"""Prototype (issue 19, part 2): ECR's model variance ``tau^2`` estimated from the data.

ECR's model is ``v_n ~ N(mu_{j_n}, s_n + tau^2)``: one mean per reference bin, ``s_n`` the pixel's noise variance,
``tau^2`` what a bin of the map does not explain. Today ``tau^2`` is fixed at ``bin_width^2 / 12``; when the scene
changed between the map and the capture the misfit is hundreds to thousands of grey levels^2, the weights
``1 / (s_n + tau^2)`` trust the quiet pixels far too much, and the per-pixel variance loses to a uniform one. Here
``tau^2`` is estimated by maximum likelihood, in three ways (see ``data_tools/yardstick/scene_change.py`` for the
measurements):

* :func:`estimate_model_variance`: on aligned pairs, the restricted (REML) or plain maximum-likelihood ``tau^2`` of
  the residuals about the per-bin weighted means (a 1-D concave-ish maximisation in ``log tau^2``: a grid, then
  golden-section refinement);
* :func:`ecr_profile_surface`: per placement, the profile likelihood maximised over ``tau^2`` on ``T`` planes
  ``tau_t^2 = V c_t`` (``V`` the captured image's spread), interpolated in ``log tau^2``, scored against the same
  profile of one mean (``H0``);
* :func:`ecr_estimated_surface`: ``tau^2`` per captured image from the residuals at the best placement of a first
  pass (the cheap few-bin stage, uniform weights or today's ``tau^2``), then the ECR surface rescored with it
  (coordinate ascent on the joint likelihood over placement and ``tau^2``; ``rounds`` of it);
* :func:`ecr_bin_variance_surface`: a variance ``tau_j^2`` per reference bin, from the first pass's best placement
  (shrunk towards the pooled one), scored by the full Gaussian log-likelihood with those variances.

Surfaces here support a captured mask and references without masked cells (every placement overlaps fully), which
is what the yardstick needs; the integration generalises the captured-only sums (the log-determinant and the total
sum of squares) to correlations with the reference mask.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from enmi_torch.binning import hard_bin_index
from enmi_torch.correlation_ratio import default_model_variance as default_model_variance_like
from enmi_torch.localization.surface import Surface, _check_inputs, _Correlator, _ecr_surface, _ReferencePlanes

_GOLDEN = (math.sqrt(5) - 1) / 2


def _bin_sums(values: Tensor, cells: Tensor, bins: int) -> Tensor:
    """Sums of ``values`` ``(..., B, N)`` per bin ``cells`` ``(B, N)``: ``(..., B, bins)``."""
    index = cells.expand(values.shape)
    return values.new_zeros(*values.shape[:-1], bins).scatter_add_(-1, index, values)


def model_variance_log_likelihood(
    captured: Tensor,
    cells: Tensor,
    variance: Tensor,
    valid: Tensor,
    tau2: Tensor,
    bins: int,
    *,
    restricted: bool = True,
) -> Tensor:
    """Profile (or restricted) Gaussian log-likelihood of ``tau^2`` on aligned pairs, up to a constant.

    ``l(tau^2) = -1/2 sum_n log(s_n + tau^2) - 1/2 sum_n w_n (v_n - mu_j)^2 [- 1/2 sum_j log W_j]`` with
    ``w_n = 1 / (s_n + tau^2)``, ``mu_j`` the weighted mean of bin ``j`` and ``W_j`` its weight (the restricted
    likelihood's term, which removes the bias of estimating ``K`` means).

    Args:
        captured: ``(B, N)`` captured values.
        cells: ``(B, N)`` reference bin of each pixel (int64).
        variance: ``(B, N)`` noise variances ``s_n`` (> 0 where valid).
        valid: ``(B, N)`` bool.
        tau2: ``(G, B)`` candidate model variances, ``>= 0``.
        bins: number of reference bins.
        restricted: add the restricted likelihood's ``-1/2 sum_j log W_j``.

    Returns:
        ``(G, B)`` log-likelihood of each candidate.
    """
    dtype = captured.dtype
    mask = valid.to(dtype)
    total = variance[None] + tau2[..., None]  # (G, B, N)
    weight = mask / total
    values = captured - (captured * mask).sum(-1, keepdim=True) / mask.sum(-1, keepdim=True).clamp_min(1)
    weight_sum = _bin_sums(weight, cells, bins)
    value_sum = _bin_sums(weight * values, cells, bins)
    occupied = _bin_sums(mask.expand(weight.shape), cells, bins) > 0.5
    between = torch.where(occupied, value_sum.square() / torch.where(occupied, weight_sum, 1.0), 0.0).sum(-1)
    residual = (weight * values.square()).sum(-1) - between
    log_det = (mask * total.log()).sum(-1)
    likelihood = -0.5 * (log_det + residual)
    if restricted:
        likelihood = likelihood - 0.5 * torch.where(occupied, torch.where(occupied, weight_sum, 1.0).log(), 0.0).sum(-1)
    return likelihood


def score_model_variance(
    captured: Tensor,
    cells: Tensor,
    variance: Tensor,
    valid: Tensor,
    bins: int,
    *,
    restricted: bool = True,
    steps: int = 4,
) -> Tensor:
    """The (restricted) maximum-likelihood ``tau^2`` ``(B,)`` by Fisher scoring (:func:`estimate_model_variance`, fast).

    From the moment estimate (unweighted bin means: mean squared residual less the mean noise variance, at least 0),
    ``steps`` updates ``tau^2 += U / I`` (clamped at 0) with the score ``U = 1/2 sum w^2 r^2 - 1/2 sum w
    [+ 1/2 sum_j sum_{n in j} w_n^2 / W_j]`` and the expected information ``I = 1/2 sum w^2``, ``w = 1 / (s + tau^2)``,
    ``r`` the residuals about the weighted bin means. Each step is three per-bin sums over the pixels.
    """
    with torch.no_grad():
        dtype = torch.float64
        captured, variance = captured.to(dtype), variance.to(dtype)
        mask = valid.to(dtype)
        count = mask.sum(-1).clamp_min(1)
        values = captured - (captured * mask).sum(-1, keepdim=True) / count[:, None]
        counts = _bin_sums(mask, cells, bins)
        means = _bin_sums(mask * values, cells, bins) / counts.clamp_min(1)
        residual = values - means.gather(1, cells)
        occupied = (counts > 0.5).sum(-1)
        moment = (mask * residual.square()).sum(-1) / (count - occupied).clamp_min(1) - (mask * variance).sum(
            -1
        ) / count
        tau2 = moment.clamp_min(0)
        for _ in range(steps):
            weight = mask / (variance + tau2[:, None])
            weight_sums = _bin_sums(weight, cells, bins)
            means = _bin_sums(weight * values, cells, bins) / weight_sums.clamp_min(1e-300)
            residual = values - means.gather(1, cells)
            squared = weight.square()
            score = 0.5 * ((squared * residual.square()).sum(-1) - weight.sum(-1))
            if restricted:
                score = score + 0.5 * (_bin_sums(squared, cells, bins) / weight_sums.clamp_min(1e-300)).sum(-1)
            tau2 = (tau2 + score / (0.5 * squared.sum(-1))).clamp_min(0)
        return tau2


def estimate_model_variance(
    captured: Tensor,
    cells: Tensor,
    variance: Tensor,
    valid: Tensor,
    bins: int,
    *,
    restricted: bool = True,
    floor: float = 0.0,
) -> Tensor:
    """The (restricted) maximum-likelihood ``tau^2`` of aligned pairs, ``(B,)``, without gradient.

    A grid of 49 values of ``log tau^2`` from ``1e-3`` to ``16 V`` (``V`` each image's spread over its valid pixels)
    brackets the maximum; 24 golden-section steps refine it (to ``1e-5`` in ``log tau^2``). The maximum at the grid's
    low end gives ``floor``.

    Args:
        captured: ``(B, N)`` captured values.
        cells: ``(B, N)`` reference bin of each pixel (int64).
        variance: ``(B, N)`` noise variances.
        valid: ``(B, N)`` bool.
        bins: number of reference bins.
        restricted: REML (default) or plain ML.
        floor: the smallest estimate returned.
    """
    with torch.no_grad():
        dtype = torch.float64
        captured, variance = captured.to(dtype), variance.to(dtype)
        mask = valid.to(dtype)
        count = mask.sum(-1).clamp_min(1)
        mean = (captured * mask).sum(-1) / count
        spread = ((captured - mean[:, None]).square() * mask).sum(-1) / count
        high = (16 * spread).clamp_min(1.0).log()
        low = torch.full_like(high, math.log(1e-3))
        steps = torch.linspace(0, 1, 49, dtype=dtype)[:, None]
        grid = low + (high - low) * steps  # (G, B)

        def curve(log_tau2: Tensor) -> Tensor:
            return model_variance_log_likelihood(
                captured, cells, variance, valid, log_tau2.exp(), bins, restricted=restricted
            )

        values = curve(grid)
        best = values.argmax(0)
        columns = torch.arange(grid.shape[1])
        left = grid[(best - 1).clamp_min(0), columns]
        right = grid[(best + 1).clamp_max(grid.shape[0] - 1), columns]
        # Golden-section search on [left, right], which holds the maximum (the curve is unimodal in practice).
        for _ in range(24):
            inner = torch.stack([right - _GOLDEN * (right - left), left + _GOLDEN * (right - left)])
            values = curve(inner)
            move_right = values[0] < values[1]
            left = torch.where(move_right, inner[0], left)
            right = torch.where(move_right, right, inner[1])
        estimate = (0.5 * (left + right)).exp()
        return torch.where(best == 0, torch.full_like(estimate, floor), estimate.clamp_min(floor))


def _flat_inputs(inputs):
    batch = inputs.captured.shape[0]
    return (
        inputs.captured.reshape(batch, -1),
        inputs.variance.reshape(batch, -1),
        inputs.captured_valid.reshape(batch, -1),
    )


def _sections_cells(inputs, placements: Tensor, bins: int, value_range) -> Tensor:
    """Reference bins under each captured image at ``placements`` ``(B, 2)`` (row, col): ``(B, N)``."""
    height, width = inputs.captured.shape[1:]
    windows = inputs.reference.shape[0]
    cells = []
    for sample, (row, col) in enumerate(placements.tolist()):
        window = inputs.reference[sample if windows > 1 else 0]
        cells.append(hard_bin_index(window[row : row + height, col : col + width], bins, value_range).flatten())
    return torch.stack(cells)


def _argmax_placements(score: Tensor) -> Tensor:
    columns = score.shape[-1]
    peak = score.flatten(1).argmax(1)
    return torch.stack([peak // columns, peak % columns], 1)


def estimate_at(inputs, placements: Tensor, bins: int, value_range, *, restricted: bool = True) -> Tensor:
    """``tau^2`` ``(B,)`` estimated from the residuals of each captured image at its placement ``(B, 2)``."""
    captured, variance, valid = _flat_inputs(inputs)
    cells = _sections_cells(inputs, placements, bins, value_range)
    return score_model_variance(captured, cells, variance, valid, bins, restricted=restricted)


def _spread(window: Tensor) -> tuple[float, float]:
    values = window.flatten().float()
    # A strided sample of at most ~2048 cells: the percentiles need not be exact, and sorting is the cost.
    low, high = torch.quantile(values[:: max(1, values.numel() // 2048)], values.new_tensor([0.02, 0.98])).tolist()
    return (low, high) if high > low else (low, low + 1.0)


def first_pass(inputs, bins: int, value_range, kind: str) -> Tensor:
    """The first pass's score ``(B, Sy, Sx)``.

    ``"cheap"``: 4 bins over the window's 2-98 % spread, counts from the weights (the two-stage search's first
    stage); ``"cheap8"``: the same with 8 bins; ``"uniform"``: one weight for all pixels; ``"default"``: today's
    ``tau^2``.
    """
    if kind in ("cheap", "cheap8"):
        cheap_bins = 4 if kind == "cheap" else 8
        scores = []
        for sample in range(inputs.captured.shape[0]):
            window = inputs.reference[sample if inputs.reference.shape[0] > 1 else 0]
            cheap_range = _spread(window)
            one = inputs._replace(
                captured=inputs.captured[sample : sample + 1],
                reference=window[None],
                captured_valid=inputs.captured_valid[sample : sample + 1],
                reference_valid=inputs.reference_valid[sample if inputs.reference.shape[0] > 1 else 0][None],
                variance=inputs.variance[sample : sample + 1],
            )
            tau2 = default_model_variance_like(cheap_bins, cheap_range)
            scores.append(_ecr_surface(one, tau2, cheap_bins, cheap_range, exact_counts=False).score[0])
        return torch.stack(scores)
    if kind == "uniform":
        return _ecr_surface(inputs._replace(variance=torch.ones_like(inputs.variance)), 0.0, bins, value_range).score
    if kind == "default":
        return _ecr_surface(inputs, default_model_variance_like(bins, value_range), bins, value_range).score
    raise ValueError(f"kind must be one of ['cheap', 'cheap8', 'uniform', 'default'], got {kind!r}")


def ecr_estimated_surface(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    captured_mask: Tensor | None = None,
    first: str = "cheap",
    rounds: int = 1,
    restricted: bool = True,
    placements: Tensor | None = None,
) -> tuple[Surface, Tensor]:
    """ECR surface with ``tau^2`` per captured image, estimated at the best placement of a first pass; ``tau^2 (B,)``.

    ``rounds`` times: estimate ``tau^2`` at the current best placement, rescore the ECR surface with it. With
    ``placements`` ``(B, 2)`` the estimate comes from those placements instead (the oracle: the true ones).
    """
    with torch.no_grad():
        inputs = _check_inputs(captured, reference, captured_mask, None, value_range, variance)
        best = (
            placements if placements is not None else _argmax_placements(first_pass(inputs, bins, value_range, first))
        )
        surface = None
        tau2 = None
        for _ in range(rounds):
            estimate = estimate_at(inputs, best, bins, value_range, restricted=restricted)
            if tau2 is not None and bool(((estimate / tau2.clamp_min(1e-12)).log().abs() < math.log(1.25)).all()):
                break
            tau2 = estimate
            surface = _ecr_surface(inputs, tau2.to(inputs.captured.dtype)[:, None, None], bins, value_range)
            best = _argmax_placements(surface.score)
        return surface, tau2


def _captured_only(inputs, tau2: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Per image and ``tau^2`` ``(T, B)``: weight planes ``(T, B, h, w)``, centred values, ``sum w v^2``, log-det."""
    dtype = inputs.captured.dtype
    valid = inputs.captured_valid.to(dtype)
    total = inputs.variance[None] + tau2[..., None, None]
    weight = valid / total
    centre = (weight * inputs.captured).sum((-2, -1), keepdim=True) / weight.sum((-2, -1), keepdim=True)
    values = inputs.captured - centre
    square = (weight * values.square()).sum((-2, -1))
    log_det = (valid * total.log()).sum((-2, -1))
    return weight, weight * values, square, log_det


def _interpolated_max(values: Tensor) -> Tensor:
    """Maximum over the first axis (equally spaced in ``log tau^2``), refined by a parabola through the best three."""
    best = values.argmax(0, keepdim=True)
    count = values.shape[0]
    peak = values.gather(0, best)[0]
    if count < 3:
        return peak
    inner = best.clamp(1, count - 2)
    left, centre, right = (values.gather(0, inner + shift)[0] for shift in (-1, 0, 1))
    curvature = left - 2 * centre + right
    vertex = centre - (right - left).square() / (8 * torch.where(curvature < 0, curvature, -1.0))
    interior = (best[0] > 0) & (best[0] < count - 1) & (curvature < 0)
    return torch.where(interior, torch.maximum(vertex, peak), peak)


def _spread_of(inputs) -> Tensor:
    valid = inputs.captured_valid.to(inputs.captured.dtype)
    count = valid.sum((-2, -1)).clamp_min(1)
    mean = (inputs.captured * valid).sum((-2, -1)) / count
    return ((inputs.captured - mean[:, None, None]).square() * valid).sum((-2, -1)) / count


def ecr_profile_surface(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    captured_mask: Tensor | None = None,
    factors: tuple[float, ...] = (1.0, 1 / 4, 1 / 16, 1 / 64, 1 / 256, 1 / 1024),
    restricted: bool = False,
) -> tuple[Surface, Tensor]:
    """ECR with ``tau^2`` maximised per placement on the planes ``tau_t^2 = V c_t`` (``V`` the image's spread).

    Per plane, the weights ``w = 1 / (s + tau_t^2)`` and weighted values correlated with each reference bin give
    the per-bin sums at every placement; the profile log-likelihood ``l1_t = -1/2 (log det + sum w v^2 -
    sum_j S_j^2 / W_j)`` is maximised over the planes (a parabola in ``log tau^2`` through the best three), and so is
    ``H0``'s (one mean). Score: ``(max l1 - max l0 - (K_occ - 1) / 2) / n``; with one plane it is ECR at that
    ``tau^2``. Also returns the ``tau^2`` of the best plane at the surface's peak ``(B,)``.
    """
    with torch.no_grad():
        inputs = _check_inputs(captured, reference, captured_mask, None, value_range, variance)
        dtype = inputs.captured.dtype
        batch, height, width = inputs.captured.shape
        scale = _spread_of(inputs)
        tau2 = torch.tensor(factors, dtype=dtype)[:, None] * scale[None]  # (T, B)
        weight, weighted_value, square, log_det = _captured_only(inputs, tau2)
        correlator = _Correlator((height, width), tuple(inputs.reference.shape[1:]))
        window_bins = torch.where(inputs.reference_valid, hard_bin_index(inputs.reference, bins, value_range), bins)
        scores, overlaps, peaks = [], [], []
        reference = None
        windows = inputs.reference.shape[0]
        planes_count = len(factors)
        for sample in range(batch):
            if reference is None or windows > 1:
                index = sample if windows > 1 else 0
                reference = _ReferencePlanes(correlator, window_bins[index], inputs.reference_valid[index], bins, dtype)
            valid = inputs.captured_valid[sample].to(dtype)
            planes = torch.cat([weight[:, sample], weighted_value[:, sample], valid[None]])
            spectra = correlator.spectra(planes, captured=True)
            sums = inputs.captured.new_empty(len(planes), reference.spectra.shape[0], correlator.rows, correlator.cols)
            for index, start, block in correlator.blocks(spectra, reference.spectra):
                sums[index, start : start + block.shape[0]] = block
            present = reference.bin_count
            count = sums[-1, :present].round()
            occupied = count > 0.5
            weight_sums = sums[:planes_count, :present]
            value_sums = sums[planes_count : 2 * planes_count, :present]
            between = torch.where(occupied, value_sums.square() / torch.where(occupied, weight_sums, 1.0), 0.0).sum(1)
            null = -0.5 * (log_det[:, sample] + square[:, sample])  # (T,): the weighted values are centred
            alternative = null[:, None, None] + 0.5 * between  # (T, rows, cols)
            overlap = count.sum(0)
            penalty = (occupied.sum(0) - 1).clamp_min(0).to(dtype)
            best_null = _interpolated_max(null[:, None, None])
            score = (_interpolated_max(alternative) - best_null - 0.5 * penalty) / overlap.clamp_min(1)
            scores.append(torch.where(overlap > 0.5, score, 0.0))
            overlaps.append(overlap)
            peak = int(score.flatten().argmax())
            peaks.append(tau2[alternative.flatten(1)[:, peak].argmax(), sample])
        return Surface(torch.stack(scores), torch.stack(overlaps)), torch.stack(peaks)


def _matched_correlations(correlator: _Correlator, captured: Tensor, reference: Tensor) -> Tensor:
    """``out[k] = correlation of captured plane k with reference plane k`` at the placements, ``(K, rows, cols)``.

    ``captured`` and ``reference`` are spectra from ``correlator.spectra`` ``(K, Q, P)``.
    """
    product = captured * reference
    rows = torch.fft.ifft(product, dim=-1, norm="forward")[..., : correlator.rows].transpose(-1, -2).contiguous()
    return torch.fft.irfft(rows, n=correlator.shape[1], dim=-1, norm="forward")[..., : correlator.cols]


def ecr_bin_variance_surface(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    captured_mask: Tensor | None = None,
    first: str = "cheap",
    prior_pixels: float = 32.0,
) -> tuple[Surface, Tensor]:
    """A model variance per reference bin ``tau_j^2``, from the first pass's best placement, then the full likelihood.

    ``tau_j^2`` is the REML estimate of bin ``j``'s residuals, shrunk towards the pooled estimate ``tau^2`` with
    ``prior_pixels`` pseudo-pixels (``(n_j tau_j^2 + p tau^2) / (n_j + p)``, computed on the log scale); bins empty
    at that placement take ``tau^2``. At every placement, with the per-bin variances, ``l1 = -1/2 sum_j (L_j +
    Q_j - S_j^2 / W_j)`` (``L_j`` the log-determinant, ``Q_j`` the weighted sum of squares of the pixels over bin
    ``j``), against ``H0`` with the pooled ``tau^2``: score ``(l1 - l0 - (K_occ - 1) / 2) / n``. Returns the surface
    and the pooled ``tau^2`` ``(B,)``.
    """
    with torch.no_grad():
        inputs = _check_inputs(captured, reference, captured_mask, None, value_range, variance)
        dtype = inputs.captured.dtype
        batch, height, width = inputs.captured.shape
        best = _argmax_placements(first_pass(inputs, bins, value_range, first))
        flat_captured, flat_variance, flat_valid = _flat_inputs(inputs)
        cells = _sections_cells(inputs, best, bins, value_range)
        pooled = estimate_model_variance(flat_captured, cells, flat_variance, flat_valid, bins)
        correlator = _Correlator((height, width), tuple(inputs.reference.shape[1:]))
        window_bins = torch.where(inputs.reference_valid, hard_bin_index(inputs.reference, bins, value_range), bins)
        windows = inputs.reference.shape[0]
        scores, overlaps = [], []
        for sample in range(batch):
            index = sample if windows > 1 else 0
            reference = _ReferencePlanes(correlator, window_bins[index], inputs.reference_valid[index], bins, dtype)
            present = reference._labels[:-1]
            per_bin = _per_bin_variances(
                flat_captured[sample],
                cells[sample],
                flat_variance[sample],
                flat_valid[sample],
                pooled[sample],
                present,
                prior_pixels,
            ).to(dtype)
            valid = inputs.captured_valid[sample].to(dtype)
            total = inputs.variance[sample][None] + per_bin[:, None, None]  # (Kp, h, w)
            weight = valid / total
            centre = (valid * inputs.captured[sample]).sum() / valid.sum()
            values = inputs.captured[sample] - centre
            planes = torch.stack(
                [weight, weight * values, weight * values.square(), valid * total.log(), valid.expand_as(weight)]
            )
            spectra = correlator.spectra(planes.flatten(0, 1), captured=True).view(
                5, len(present), *correlator_shape(correlator)
            )
            reference_spectra = reference.spectra[: len(present)]
            sums = torch.stack([_matched_correlations(correlator, spectra[k], reference_spectra) for k in range(5)])
            weight_sums, value_sums, squares, log_dets, count = sums
            count = count.round()
            occupied = count > 0.5
            between = torch.where(occupied, value_sums.square() / torch.where(occupied, weight_sums, 1.0), 0.0)
            alternative = -0.5 * (log_dets.sum(0) + squares.sum(0) - between.sum(0))
            null_total = inputs.variance[sample] + pooled[sample].to(dtype)
            null_weight = valid / null_total
            null_mean = (null_weight * values).sum() / null_weight.sum()
            null = -0.5 * ((valid * null_total.log()).sum() + (null_weight * (values - null_mean).square()).sum())
            overlap = count.sum(0)
            penalty = (occupied.sum(0) - 1).clamp_min(0).to(dtype)
            score = (alternative - null - 0.5 * penalty) / overlap.clamp_min(1)
            scores.append(torch.where(overlap > 0.5, score, 0.0))
            overlaps.append(overlap)
        return Surface(torch.stack(scores), torch.stack(overlaps)), pooled


def correlator_shape(correlator: _Correlator) -> tuple[int, int]:
    """The transposed half spectrum's shape ``(Q, P)`` of ``correlator``'s planes."""
    return correlator.shape[1] // 2 + 1, correlator.shape[0]


def _per_bin_variances(captured, cells, variance, valid, pooled, present, prior_pixels) -> Tensor:
    """``tau_j^2`` for the ``present`` bins: per-bin REML estimates shrunk towards ``pooled`` on the log scale."""
    estimates = []
    mask = valid
    for label in present.tolist():
        members = mask & (cells == label)
        count = int(members.sum())
        if count < 2:
            estimates.append(pooled)
            continue
        single = estimate_model_variance(
            captured[members][None],
            torch.zeros(1, count, dtype=torch.long),
            variance[members][None],
            torch.ones(1, count, dtype=torch.bool),
            1,
        )[0]
        weight = count / (count + prior_pixels)
        estimates.append(torch.exp(weight * single.clamp_min(1e-3).log() + (1 - weight) * pooled.clamp_min(1e-3).log()))
    return torch.stack(estimates)


def _residuals(inputs, placements: Tensor, total: Tensor, bins: int, value_range) -> Tensor:
    """Residuals ``(B, h, w)`` of each captured image about its bins' means weighted by ``1 / total`` ``(B, h, w)``."""
    captured, _, valid = _flat_inputs(inputs)
    cells = _sections_cells(inputs, placements, bins, value_range)
    weight = valid.to(captured.dtype) / total.reshape(captured.shape)
    means = _bin_sums(weight * captured, cells, bins) / _bin_sums(weight, cells, bins).clamp_min(1e-30)
    return (captured - means.gather(1, cells)).where(valid, 0.0).view_as(inputs.captured)


def _gaussian_smooth(planes: Tensor, sigma: float) -> Tensor:
    """Gaussian blur of ``(B, h, w)`` planes with zero padding (divide by the blurred mask to normalise)."""
    radius = max(1, math.ceil(3 * sigma))
    taps = torch.arange(-radius, radius + 1, dtype=planes.dtype)
    kernel = torch.exp(-0.5 * (taps / sigma) ** 2)
    kernel = kernel / kernel.sum()
    out = torch.nn.functional.conv2d(planes[:, None], kernel.view(1, 1, 1, -1), padding=(0, radius))
    return torch.nn.functional.conv2d(out, kernel.view(1, 1, -1, 1), padding=(radius, 0))[:, 0]


def local_model_variance(
    inputs, placements: Tensor, bins: int, value_range, *, kind: str = "fisher", scale: float = 3.0, iterations: int = 1
) -> tuple[Tensor, Tensor]:
    """Model variance per captured pixel ``tau_n^2`` ``(B, h, w)`` from residuals at ``placements``; pooled ``(B,)``.

    The pooled ``tau^2`` (REML) and the per-bin weighted means at the placement give residuals ``r_n``. ``kind``:

    * ``"smooth"``: ``tau_n^2 = max(0, G * (r^2 - s) / G * 1)`` over the valid pixels, ``G`` a Gaussian of standard
      deviation ``scale`` pixels (the misfit varies in space: occluders, shadows, changed ground);
    * ``"fisher"``: the same with each pixel weighted by its Fisher information about ``tau^2``, ``1 / (s + tau^2)^2``
      (one Fisher-scoring step of the local likelihood from the pooled ``tau^2``): noisy pixels lend little;
    * ``"eb"``: ``"fisher"`` shrunk towards the pooled ``tau^2`` by empirical Bayes: ``tau^2 + l_n (local - tau^2)``,
      ``l_n = V / (V + e_n)`` with ``e_n`` the local estimate's sampling variance (Gaussian residuals) and ``V`` the
      spread of the local estimates over the image less their mean sampling variance (0: one ``tau^2`` for all);
    * ``"student"``: the weight of a Student-t with ``scale`` degrees of freedom, ``w_n = (nu + 1) / (nu + r_n^2 /
      (s_n + tau^2)) / (s_n + tau^2)``, as a total variance ``1 / w_n`` less ``s_n``.

    ``iterations`` > 1 recomputes the bin means with the new weights and the local variances from their residuals.
    """
    pooled = estimate_at(inputs, placements, bins, value_range)
    valid = inputs.captured_valid.to(inputs.captured.dtype)
    noise = inputs.variance
    total = noise + pooled.to(noise.dtype)[:, None, None]
    base = total
    for _ in range(iterations):
        residual = _residuals(inputs, placements, total, bins, value_range)
        if kind == "smooth":
            excess = _gaussian_smooth(valid * (residual.square() - noise), scale)
            local = (excess / _gaussian_smooth(valid, scale).clamp_min(1e-12)).clamp_min(0)
        elif kind == "fisher":
            information = valid / base.square()
            excess = _gaussian_smooth(information * (residual.square() - noise), scale)
            local = (excess / _gaussian_smooth(information, scale).clamp_min(1e-300)).clamp_min(0)
        elif kind == "eb":
            local = _shrunk_local(residual, noise, valid, base, pooled.to(noise.dtype), scale)
        elif kind == "student":
            local = (base * (scale + residual.square() / base) / (scale + 1) - noise).clamp_min(0)
        else:
            raise ValueError(f"kind must be 'smooth', 'fisher' or 'student', got {kind!r}")
        total = noise + local
    return torch.where(inputs.captured_valid, total - noise, 0.0), pooled


def _shrunk_local(residual, noise, valid, base, pooled, scale) -> Tensor:
    """Empirical-Bayes local ``tau_n^2``: Fisher-weighted local moments shrunk towards ``pooled`` ``(B,)``."""
    information = valid / base.square()
    weight_sum = _gaussian_smooth(information, scale).clamp_min(1e-300)
    local = _gaussian_smooth(information * (residual.square() - noise), scale) / weight_sum
    # Var(r^2) = 2 (s + tau^2)^2 per pixel: the local estimate's variance is 2 sum g^2 w^2 / (sum g w^2)^2.
    squared_kernel_sum = _gaussian_smooth(information * base.square() * information, scale / math.sqrt(2))
    norm = 1 / (2 * math.sqrt(math.pi) * scale)  # sum of g^2 relative to a Gaussian of sigma / sqrt(2), per axis
    sampling = 2 * squared_kernel_sum * norm**2 / weight_sum.square()
    count = valid.sum((-2, -1)).clamp_min(1)
    mean = (valid * local).sum((-2, -1)) / count
    spread = (valid * (local - mean[:, None, None]).square()).sum((-2, -1)) / count
    between = (spread - (valid * sampling).sum((-2, -1)) / count).clamp_min(0)[:, None, None]
    share = between / (between + sampling).clamp_min(1e-300)
    return (pooled[:, None, None] + share * (local - pooled[:, None, None])).clamp_min(0)


def separated_peaks(score: Tensor, count: int, radius: int = 2) -> Tensor:
    """The ``count`` best placements ``(count, B, 2)`` of ``score`` ``(B, Sy, Sx)``, each ``radius`` cells apart."""
    score = score.clone()
    peaks = []
    for _ in range(count):
        peak = _argmax_placements(score)
        peaks.append(peak)
        for sample, (row, col) in enumerate(peak.tolist()):
            score[sample, max(0, row - radius) : row + radius + 1, max(0, col - radius) : col + radius + 1] = -math.inf
    return torch.stack(peaks)


def field_log_likelihood(inputs, placements: Tensor, total: Tensor, bins: int, value_range) -> Tensor:
    """Gaussian log-likelihood ``(B,)`` of the captured images at ``placements`` with variances ``total`` (h, w).

    ``-1/2 sum_n (log total_n + r_n^2 / total_n)`` over the valid pixels, ``r_n`` the residuals about the bins'
    weighted means (profiled).
    """
    residual = _residuals(inputs, placements, total, bins, value_range)
    valid = inputs.captured_valid.to(residual.dtype)
    return -0.5 * (valid * (total.log() + residual.square() / total)).sum((-2, -1))


def ecr_local_surface(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    captured_mask: Tensor | None = None,
    first: str = "cheap",
    kind: str = "fisher",
    scale: float = 3.0,
    iterations: int = 1,
    rounds: int = 1,
    placements: Tensor | None = None,
    candidates: int = 1,
    select: str = "field",
) -> tuple[Surface, Tensor]:
    """ECR with a model variance per captured pixel (:func:`local_model_variance`) at a first pass's best placement.

    The ECR surface with ``variance = s + tau_n^2`` (model variance 0); ``rounds`` > 1 re-estimates at the new best
    placement and rescores. With ``candidates`` > 1, the field is fitted at each of the first pass's best separated
    placements and the one of highest likelihood (:func:`field_log_likelihood`) is kept (joint maximum likelihood
    over placement and field among the candidates; ``select="pooled"``: with one ``tau^2`` per candidate, the profile
    likelihood over placement and ``tau^2``). Returns the surface and the pooled ``tau^2`` ``(B,)``.
    """
    with torch.no_grad():
        inputs = _check_inputs(captured, reference, captured_mask, None, value_range, variance)
        if placements is not None:
            best = placements
        elif candidates == 1:
            best = _argmax_placements(first_pass(inputs, bins, value_range, first))
        else:
            peaks = separated_peaks(first_pass(inputs, bins, value_range, first), candidates)
            likelihoods = []
            for peak in peaks:
                if select == "pooled":
                    pooled = estimate_at(inputs, peak, bins, value_range).to(inputs.variance.dtype)
                    total = inputs.variance + pooled[:, None, None]
                else:
                    local, _ = local_model_variance(
                        inputs, peak, bins, value_range, kind=kind, scale=scale, iterations=iterations
                    )
                    total = torch.where(inputs.captured_valid, inputs.variance + local, 1.0)
                likelihoods.append(field_log_likelihood(inputs, peak, total, bins, value_range))
            choice = torch.stack(likelihoods).argmax(0)
            best = peaks[choice, torch.arange(peaks.shape[1])]
        for _ in range(rounds):
            local, pooled = local_model_variance(
                inputs, best, bins, value_range, kind=kind, scale=scale, iterations=iterations
            )
            total = torch.where(inputs.captured_valid, inputs.variance + local, 1.0)
            surface = _ecr_surface(inputs._replace(variance=total), 0.0, bins, value_range)
            best = _argmax_placements(surface.score)
        return surface, pooled
