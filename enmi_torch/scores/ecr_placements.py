"""ECR over every placement: the FFT surface, the first pass that places the estimates, the two-stage search's stages.

Per placement ECR needs, per reference bin ``j``, the count, the weight sum ``W_j`` and the weighted value sum ``S_j``
of the captured pixels over it: three correlations of captured planes (valid mask, weights, weighted values) with each
bin's indicator plane (:mod:`enmi_torch.placement`), ``3 K`` inverse FFTs. The linear response takes nine correlations
of captured and reference planes, whatever the bins.

A surface's estimated ``tau^2`` and ``delta^2`` (:mod:`~enmi_torch.scores.ecr_model_variance`) are read at the best
placement of a cheap first pass: :data:`FIRST_PASS_BINS` bins over the window's 2nd to 98th percentile
(:func:`cheap_value_range`, as the two-stage search's first stage), among the placements that overlap at least half
the captured image. Each captured image of a batch has its own.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from enmi_torch.binning import hard_bin_index
from enmi_torch.placement.fft import Correlator
from enmi_torch.placement.inputs import Surface, SurfaceInputs, check_inputs
from enmi_torch.placement.planes import moment_blocks, per_sample_reference_planes
from enmi_torch.scores.censoring import check_saturation, saturated_pixels
from enmi_torch.scores.ecr_censored import censored_ecr
from enmi_torch.scores.ecr_model_variance import (
    MISFITS,
    MODEL_VARIANCE_ESTIMATE,
    RESPONSE_VARIANCE_ESTIMATE,
    check_model_variance,
    check_response_variance,
    default_model_variance,
    estimated_model_variance,
    estimated_response_variance,
)
from enmi_torch.scores.ecr_statistics import RESPONSES, BinSums, ecr_from_bin_sums, ecr_from_sums, linear_llr
from enmi_torch.scores.shrunk_response import bin_positions
from enmi_torch.utils.budget import check_surface_memory
from enmi_torch.utils.checks import check_bins, check_option, check_value_range, check_variance_given

# Bins of the cheap first pass whose best placement a surface's estimated tau^2 is read at (the two-stage search's).
FIRST_PASS_BINS = 4


def cheap_value_range(window: Tensor, window_valid: Tensor) -> tuple[float, float]:
    """The 2nd to 98th percentile of a map window's valid cells: the range over which a cheap stage's few bins split it.

    Example:
        >>> window = torch.arange(101.0).reshape(1, 1, 1, 101)
        >>> cheap_value_range(window, window >= 0)
        (2.0, 98.0)
    """
    values = window[window_valid].float()
    if values.numel() == 0:
        return (0.0, 1.0)
    low, high = torch.quantile(values[:: max(1, values.numel() // 65536)], values.new_tensor([0.02, 0.98])).tolist()
    return (low, high) if high > low else (low, low + 1.0)


def check_surface_inputs(
    captured,
    reference,
    variance,
    bins,
    value_range,
    model_variance,
    captured_mask,
    reference_mask,
    response,
    misfit,
    saturation="value_range",
):
    """The checked inputs, bins and value range of :func:`~enmi_torch.scores.ecr.ecr_surface` (its arguments)."""
    check_variance_given(variance)
    bins = check_bins(bins)
    value_range = check_value_range(value_range)
    check_model_variance(model_variance, bins, value_range)
    check_option("response", response, RESPONSES)
    check_option("misfit", misfit, MISFITS)
    check_saturation(saturation)
    binned = None if response == "linear" else bins  # the map is binned: refuse one that all falls in one bin
    inputs = check_inputs(
        captured, reference, captured_mask, reference_mask, value_range, variance, reference_bins=binned
    )
    check_surface_memory(inputs.captured, inputs.reference, bins)
    return inputs, bins, value_range


def _first_pass(inputs: SurfaceInputs) -> Tensor:
    """The cheap first pass's ECR ``(B, Sy, Sx)``, ``-inf`` where less than half the captured image overlaps.

    :data:`FIRST_PASS_BINS` bins over each window's 2nd to 98th percentile (:func:`cheap_value_range`), their default
    model variance, the occupied bins read from the weight sums (as the two-stage search's first stage). Where no
    placement overlaps half the image, those of the largest overlap count.
    """
    windows, batch = inputs.reference.shape[0], inputs.captured.shape[0]
    groups = [slice(None)] if windows == 1 else [slice(sample, sample + 1) for sample in range(batch)]
    scores = []
    for group in groups:
        window, window_valid = inputs.reference[group][:1], inputs.reference_valid[group][:1]
        value_range = cheap_value_range(window, window_valid)
        part = SurfaceInputs(
            inputs.captured[group], window, inputs.captured_valid[group], window_valid, inputs.variance[group]
        )
        tau2 = default_model_variance(FIRST_PASS_BINS, value_range)
        surface = ecr_surface_from_inputs(part, tau2, FIRST_PASS_BINS, value_range, exact_counts=False)
        half = 0.5 * part.captured_valid.sum((-2, -1)).to(surface.overlap.dtype)
        needed = torch.minimum(half, surface.overlap.amax((-2, -1))).clamp_min(1)[:, None, None]
        scores.append(torch.where(surface.overlap >= needed - 0.5, surface.score, -math.inf))
    return torch.cat(scores)


def variances_at_peaks(
    inputs: SurfaceInputs,
    scores: Tensor,
    bins: int,
    value_range: tuple[float, float],
    response: str,
    misfit: str,
    model_variance: float | str = MODEL_VARIANCE_ESTIMATE,
    saturation=None,
) -> tuple[Tensor, Tensor]:
    """``tau^2`` and ``delta^2`` ``(B,)`` float64 at each captured image's best placement in ``scores`` ``(B, Sy, Sx)``.

    ``tau^2``: the estimate there (``model_variance="estimate"``) or the fixed number; a captured image without a
    finite score gets the floor, ``bin_width^2 / 12``, with any misfit (a regional misfit: a map ``(B, h w)``, the
    floor at every pixel). ``delta^2``: the shrunk response's
    (:func:`~enmi_torch.scores.ecr_model_variance.estimated_response_variance`) with that ``tau^2``; 0 without a
    finite score. ``saturation``: the saturated readings (:mod:`~enmi_torch.scores.censoring`) both estimates treat
    as censored.
    """
    batch, height, width = inputs.captured.shape
    device = inputs.captured.device
    peak = scores.flatten(1).argmax(1)
    rows = (peak // scores.shape[-1])[:, None, None] + torch.arange(height, device=device)[:, None]
    cols = (peak % scores.shape[-1])[:, None, None] + torch.arange(width, device=device)
    window = torch.arange(batch, device=device) if inputs.reference.shape[0] > 1 else peak.new_zeros(batch)
    under = (window[:, None, None], rows, cols)
    found = torch.isfinite(scores.flatten(1).amax(1))[:, None, None]
    valid = inputs.captured_valid & inputs.reference_valid[under] & found
    flat = [part.reshape(batch, -1) for part in (inputs.captured, inputs.reference[under], inputs.variance, valid)]
    readings = flat[0].detach().to(torch.float64)
    captured_valid = inputs.captured_valid.reshape(batch, -1)
    saturated = saturated_pixels(readings, captured_valid, saturation, value_range, bins)
    side = saturated.side if saturated.any else None
    if model_variance == MODEL_VARIANCE_ESTIMATE:
        tau2 = estimated_model_variance(*flat, bins, value_range, response, (height, width), misfit, side)
    else:
        tau2 = torch.full((batch,), float(model_variance), dtype=torch.float64, device=device)
    if side is None:
        return tau2, estimated_response_variance(*flat, tau2, bins, value_range)
    with torch.no_grad():
        _, reference, noise, mask = (part.detach().to(torch.float64) for part in flat)
        total = noise + (tau2 if tau2.dim() == 2 else tau2[:, None])
        _, delta2 = censored_ecr(
            readings, reference, total, mask, side, bins, value_range, "shrunk", RESPONSE_VARIANCE_ESTIMATE
        )
    return tau2, delta2


def surface_variances(
    inputs: SurfaceInputs,
    model_variance,
    response_variance,
    bins: int,
    value_range: tuple[float, float],
    response: str,
    misfit: str = "independent",
    saturation=None,
) -> tuple[float | Tensor, float | Tensor | None]:
    """A surface's ``tau^2`` and ``delta^2``: each the fixed number or the estimate per captured image ``(B, 1, 1)``.

    A regional misfit's ``tau^2`` estimate is a map over each captured image, ``(B, h, w)``.
    Both estimates are read at the best placement of one cheap first pass, the ``saturation``'s readings censored
    there; ``delta^2`` is ``None`` unless the response is shrunk and ``response_variance`` given (it is then checked).
    """
    tau2 = check_model_variance(model_variance, bins, value_range)
    shrunk = response == "shrunk" and response_variance is not None
    delta2 = check_response_variance(response_variance) if shrunk else None
    if tau2 != MODEL_VARIANCE_ESTIMATE and delta2 != RESPONSE_VARIANCE_ESTIMATE:
        return tau2, delta2
    tau2_at, delta2_at = variances_at_peaks(
        inputs, _first_pass(inputs), bins, value_range, response, misfit, tau2, check_saturation(saturation)
    )
    dtype = inputs.captured.dtype
    if tau2 == MODEL_VARIANCE_ESTIMATE:
        tau2 = (
            tau2_at.to(dtype).view(inputs.captured.shape) if misfit == "regional" else tau2_at.to(dtype)[:, None, None]
        )
    if delta2 == RESPONSE_VARIANCE_ESTIMATE:
        delta2 = delta2_at.to(dtype)[:, None, None]
    return tau2, delta2


def ecr_surface_from_inputs(
    inputs: SurfaceInputs,
    model_variance: float | Tensor,
    bins: int,
    value_range: tuple[float, float],
    *,
    exact_counts: bool = True,
    response_variance: float | Tensor | None = None,
) -> Surface:
    """ECR at every placement from the per-bin correlations of the captured count, weight and weighted-value planes.

    ``model_variance``: a number, one per captured image ``(B, 1, 1)`` or one per captured pixel ``(B, h, w)``;
    ``response_variance``: the shrunk response's
    ``delta^2``, a number or one per captured image ``(B, 1, 1)`` (``None``: the binned response).

    With ``exact_counts=False`` (the two-stage search's cheap stage) and a reference without masked cells the per-bin
    counts are not correlated (two thirds of the correlations): a bin counts as occupied where its weight sum exceeds
    half the smallest pixel weight (FFT round-off can flip a few), and the overlap is the captured pixel count.
    """
    _, height, width = inputs.captured.shape
    correlator = Correlator((height, width), tuple(inputs.reference.shape[1:]))
    dtype = inputs.captured.dtype
    valid = inputs.captured_valid.to(dtype)
    weight = valid / (inputs.variance + model_variance)
    # Centring on the weighted mean keeps S_j^2 / W_j - S^2 / W free of cancellation; the score does not depend on it.
    centre = (weight * inputs.captured).sum((-2, -1), keepdim=True) / weight.sum((-2, -1), keepdim=True)
    weighted_value = weight * (inputs.captured - centre)
    scores, overlaps = [], []
    for sample, reference in per_sample_reference_planes(correlator, inputs, bins, value_range):
        # The counts come from the valid plane's correlations, rounded (exact): cheaper than the box sums of the planes.
        with_valid = exact_counts or not reference.complete
        planes = torch.stack([weight[sample], weighted_value[sample]] + ([valid[sample]] if with_valid else []))
        captured = correlator.spectra(planes, captured=True)
        sums = inputs.captured.new_empty(len(planes), reference.spectra.shape[0], correlator.rows, correlator.cols)
        for index, start, block in correlator.blocks(captured, reference.spectra):
            sums[index, start : start + block.shape[0]] = block
        present = reference.bin_count
        if with_valid:
            count = sums[2, :present].round()
            overlap = count.sum(0)
        else:
            smallest = weight[sample][inputs.captured_valid[sample]].amin()
            count = (sums[0, :present] > 0.5 * smallest).to(dtype)
            overlap = valid[sample].sum().expand(count.shape[1:])  # every placement lies on valid cells
        positions = None
        if response_variance is not None:
            delta2 = response_variance[sample] if isinstance(response_variance, Tensor) else response_variance
            positions = (bin_positions(bins, dtype, count.device)[reference.present_bins], value_range, delta2)
        scores.append(ecr_from_sums(count, sums[0, :present], sums[1, :present], 0, overlap, positions))
        overlaps.append(overlap)
    return Surface(torch.stack(scores), torch.stack(overlaps))


def linear_ecr_surface_from_inputs(inputs: SurfaceInputs, model_variance: float | Tensor) -> Surface:
    """ECR of the increasing affine response at every placement: weighted sums from correlations of planes."""
    valid = inputs.captured_valid.to(inputs.captured.dtype)
    weight = valid / (inputs.variance + model_variance)
    centre = (weight * inputs.captured).sum((-2, -1), keepdim=True) / weight.sum((-2, -1), keepdim=True)
    planes = torch.stack([weight, weight * (inputs.captured - centre), valid], dim=1)
    scores, overlaps = [], []
    for block in moment_blocks(inputs, planes):
        count = block[2, 0].round()
        llr = linear_llr(block[0, 0], block[1, 0], block[0, 1], block[0, 2], block[1, 1])
        scores.append(torch.where(count > 0, (llr - 0.5) / count.clamp_min(1), 0.0))
        overlaps.append(count)
    return Surface(torch.stack(scores), torch.stack(overlaps))


def rough_ecr_surface(inputs: SurfaceInputs, options: dict) -> Surface:
    """ECR at every placement of checked ``inputs`` with the occupied bins read from the weight sums: a cheap stage.

    ``options``: an :class:`~enmi_torch.ECR`'s (binned or shrunk response). It ranks with free bin means (the binned
    response) whether the score is binned or shrunk: a cheap stage's few bins leave little to shrink. Without masked
    reference cells the per-bin counts are not correlated (two thirds of the correlations): a bin counts as occupied
    where its weight sum exceeds half the smallest pixel weight (FFT round-off can flip a few), and the overlap is the
    captured pixel count.
    """
    bins, value_range = options["bins"], options["value_range"]
    with torch.no_grad():
        names = ("model_variance", "response", "misfit", "saturation")
        model_variance, response, misfit, saturation = (options[name] for name in names)
        tau2 = surface_variances(inputs, model_variance, None, bins, value_range, response, misfit, saturation)[0]
        return ecr_surface_from_inputs(inputs, tau2, bins, value_range, exact_counts=False)


def ecr_placement_scores(
    placements: Tensor, rotations: tuple, window: tuple, min_overlap: float, rough: Tensor, options: dict
) -> Tensor:
    """Exact ECR ``(P,)`` of rotated captured images at placements ``(P, 3)`` (yaw index, row, column).

    As :func:`~enmi_torch.scores.ecr.ecr_surface` and the search's surfaces score them: weights
    ``1 / (variance + tau^2)`` over the captured valid pixels, values centred on each rotation's weighted mean, ``-inf``
    below ``min_overlap`` or for a rotation without a valid pixel.

    Args:
        placements: ``(P, 3)`` int64 yaw index, row and column of each placement.
        rotations: the captured images, variances and masks, ``(Y, 1, h, w)`` each.
        window: the reference window and its mask, ``(1, 1, Hw, Ww)`` each.
        min_overlap: the fraction of a rotation's valid pixels that must land on valid cells.
        rough: the search's cheap surface ``(Y, Sy, Sx)`` (``-inf`` below ``min_overlap``): an estimated ``tau^2`` (and
            ``delta^2``) is read at each rotation's best placement there (the floor for a rotation without a finite
            one).
        options: an :class:`~enmi_torch.ECR`'s (binned or shrunk response).

    Per shift, one matrix product of the rotations' count, weight and weighted-value planes with the one-hot reference
    bins under the image (unmapped cells in a bin left out) gives the per-bin sums.
    """
    captured, variance, valid = rotations
    reference, reference_valid = window
    dtype = torch.float64 if captured.dtype == torch.float64 else torch.float32
    height, width = captured.shape[2:]
    bins, value_range = options["bins"], options["value_range"]
    tau2 = check_model_variance(options["model_variance"], bins, value_range)
    delta2 = options["response_variance"] if options["response"] == "shrunk" else None
    yaws, yaw_index = torch.unique(placements[:, 0], return_inverse=True)  # only the rotations rescored
    if MODEL_VARIANCE_ESTIMATE in (tau2, delta2):
        rotated = SurfaceInputs(
            captured[yaws, 0].to(dtype),
            reference[:, 0].to(dtype),
            valid[yaws, 0],
            reference_valid[:, 0],
            variance[yaws, 0].to(dtype),
        )
        tau2_at, delta2_at = variances_at_peaks(
            rotated, rough[yaws], bins, value_range, options["response"], options["misfit"], tau2, options["saturation"]
        )
        if tau2 == MODEL_VARIANCE_ESTIMATE:
            tau2 = tau2_at.to(dtype) if options["misfit"] == "regional" else tau2_at.to(dtype)[:, None]
        if delta2 == RESPONSE_VARIANCE_ESTIMATE:
            delta2 = delta2_at.to(dtype)[yaw_index]
    valid = valid[yaws, 0].flatten(1).to(dtype)
    weight = valid / (variance[yaws, 0].to(dtype).flatten(1) + tau2)
    values = captured[yaws, 0].to(dtype).flatten(1)
    centre = (weight * values).sum(1, keepdim=True) / weight.sum(1, keepdim=True).clamp_min(torch.finfo(dtype).tiny)
    planes = torch.stack([valid, weight, weight * (values - centre)], 1)  # (Y, 3, N)
    reference_bins = torch.where(reference_valid, hard_bin_index(reference, bins, value_range), bins)[0, 0]
    section_bins = reference_bins.unfold(0, height, 1).unfold(1, width, 1)
    shifts, shift_index = torch.unique(placements[:, 1:], dim=0, return_inverse=True)
    order = shift_index.argsort()
    sums = planes.new_empty(placements.shape[0], 3, bins + 1)
    one_hot = planes.new_zeros(height * width, bins + 1)
    for (row, col), members in zip(
        shifts.tolist(), order.split(torch.bincount(shift_index, minlength=len(shifts)).tolist()), strict=True
    ):
        cells = section_bins[row, col].reshape(-1, 1)
        one_hot.scatter_(1, cells, 1.0)
        sums[members] = planes[yaw_index[members]] @ one_hot
        one_hot.scatter_(1, cells, 0.0)  # cheaper than clearing the whole matrix
    shrunk = {"value_range": value_range, "response_variance": "estimate" if delta2 is None else delta2}
    score = ecr_from_bin_sums(BinSums(*sums[..., :bins].unbind(1)), response=options["response"], **shrunk)
    needed = min_overlap * valid.sum(1)[yaw_index]
    count = sums[:, 0, :bins].sum(1)
    return torch.where((count >= needed - 0.5) & (needed > 0), score, -math.inf)


def scores_with_surface_variances(score, inputs: SurfaceInputs):
    """The direct surface's pair score with the ``tau^2`` and ``delta^2`` each captured image's surface estimates.

    An :class:`~enmi_torch.ECR` per captured image with them fixed (a regional ``tau^2`` map added to the image's
    noise variance, with a model variance of 0) and every reading a Gaussian value, as the surface scores it.
    """
    names = ("model_variance", "response_variance", "bins", "value_range", "response", "misfit", "saturation")
    tau2, delta2 = surface_variances(inputs, *(score.options[name] for name in names))
    batch = inputs.captured.shape[0]
    regional = isinstance(tau2, Tensor) and score.options["misfit"] == "regional"

    def per_sample(value) -> list:
        return torch.as_tensor(value, dtype=torch.float64).flatten().expand(batch).tolist()

    fixed = {"misfit": "independent", "saturation": None}  # the surface scores every reading as a Gaussian value
    shrinks = [None] * batch if delta2 is None else per_sample(delta2)
    models = [0.0] * batch if regional else per_sample(tau2)
    samples = [
        score.replace(model_variance=model, **fixed, **({} if shrink is None else {"response_variance": shrink}))
        for model, shrink in zip(models, shrinks, strict=True)
    ]

    def pair_score(sample: int, captured: Tensor, section: Tensor, variance: Tensor | None, valid: Tensor):
        if regional:
            variance = variance + tau2[sample].to(variance.dtype)
        return samples[sample](captured, section, variance, valid_mask=valid)[0]

    return pair_score
