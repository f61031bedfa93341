"""ECR, the enhanced (noise-aware) correlation ratio: a Gaussian log-likelihood ratio with per-pixel noise variance.

Model: the sensor sees a function of the map, blurred by noise whose variance is known per pixel. A captured pixel
``v_n`` over a reference pixel in bin ``j_n`` is ``v_n ~ N(mu_{j_n}, sigma_n^2 + tau^2)``, one unknown mean per
reference bin (any response, monotonic or not), ``sigma_n^2`` the pixel's noise variance (analytic or learned) and
``tau^2`` the model variance (what a bin of the map does not explain; by default estimated from the data, see below,
at least the spread of an amplitude uniform in a bin, ``bin_width^2 / 12``). The alternative is one mean for all
pixels (captured independent of the map). With weights ``w_n = 1 / (sigma_n^2 + tau^2)`` and per-bin sums
``W_j = sum w_n``, ``S_j = sum w_n v_n``, the maximised log-likelihood ratio is

    ``LLR = (sum_j S_j^2 / W_j - S^2 / W) / 2`` (``S``, ``W`` the sums over all bins),

the weighted between-bin sum of squares (generalised least squares). When the captured values are noise of the
stated variances around one level, ``2 LLR`` is ``chi^2`` with ``K_occ - 1`` degrees of freedom (``K_occ`` the
occupied reference bins) whatever the variances, so ``ECR = (LLR - (K_occ - 1) / 2) / n`` (``n`` the valid pixels)
has mean 0; a captured image with structure of its own that is unrelated to the reference scores about
``(K_occ - 1) / (2 n)`` times its spread over the noise variance, small against an aligned placement's score and
without a term that follows the map's content. A noisy pixel adds its evidence in proportion to its precision
instead of a full unit of histogram weight, which is what makes the per-pixel variance pay (see
``data_tools/yardstick/yardstick.py`` and ``data_tools/yardstick/diagnose_enmi.py``).

With one variance for all pixels, ``ECR = eta^2 Var[v] / (2 (sigma^2 + tau^2)) - (K_occ - 1) / (2 n)`` with
``eta^2`` the classic correlation ratio (Pearson, Roche et al. 1998) of the captured image given the reference bins.

The model variance ``tau^2`` is what a bin of the map leaves unexplained: the quantisation, ``bin_width^2 / 12``, where
the map explains the captured image up to the sensor noise; hundreds to thousands of grey levels^2 where the scene
changed (shadows, cars, another date, another modality). Too small a ``tau^2`` trusts the quiet pixels far more than
the misfit allows, and a per-pixel variance then loses to a uniform one (``data_tools/yardstick/scene_change.py``).
``model_variance="estimate"`` (the default) estimates it from the data, one ``tau^2`` per captured image, by
restricted maximum likelihood (REML: the likelihood of the residuals about the fitted bin means, which does not take
the ``K_occ`` fitted means for evidence against ``tau^2``), at least ``bin_width^2 / 12``:

* on aligned pairs (:func:`ecr`, :func:`ecr_loss`): at the given alignment (each candidate reference its own), without
  gradient; the score is ECR with that ``tau^2`` (differentiable in ``captured`` and ``variance`` as before);
* over every placement (:func:`ecr_surface`): at the best placement of a cheap first pass (:data:`FIRST_PASS_BINS`
  bins over the window's 2nd to 98th percentile, as the two-stage search's first stage) among the placements that
  overlap at least half the captured image; the surface is ECR with that ``tau^2`` at every placement. Each captured
  image of a batch has its own (in :func:`~enmi_torch.localize`: each yaw);
* in the two-stage search: at the best placement of its cheap stage, per yaw.

A changed scene's misfit is spatially correlated: a new building, a shadow or a parked car covers many neighbouring
pixels, and the per-pixel model counts each quiet pixel of such a patch as independent evidence. ``misfit="correlated"``
takes the misfit beyond the bins' quantisation as one value per block of ``m`` pixels: a pixel's weight becomes
``1 / (sigma_n^2 + m tau^2)``, so a block of ``m`` pixels of noise ``sigma^2`` weighs ``1 / (tau^2 + sigma^2 / m)``,
the generalised-least-squares weight of its mean. ``m``, the pixels per independent misfit (:func:`misfit_extent`), is
read from the residuals' autocovariance where ``tau^2`` is estimated (the sensor noise is white and adds to lag 0
only). The model variance is then ``q + m (tau^2 - q)``, ``q = bin_width^2 / 12`` the quantisation floor, which stays
per pixel as in the independent model (a smooth map's within-bin variation is correlated too, but it is the bins'
resolution, not a change of the scene). Where the misfit outweighs the noise the weights are nearly uniform, and the
log-likelihood ratio is about ``m`` times smaller: evidence counted per independent patch instead of per pixel. On
drives over real photographs of two dates it is the better tracker; on simulated drives with a light scene change it
is within one cell less often (``data_tools/README.md``, "Tracking a drive"), so ``"independent"`` stays the default.

REML by Fisher scoring: with ``w_n = 1 / (sigma_n^2 + tau^2)``, ``r_n`` the residuals about the weighted bin means and
``W_j`` the bins' weight sums, the score ``U = (sum w^2 r^2 - sum w + sum_j sum_{n in j} w_n^2 / W_j) / 2`` over the
information ``I = sum w^2 / 2`` moves ``tau^2`` from the moment estimate (the residual variance about the plain bin
means less the mean noise variance) until it settles. With ``response="linear"`` the fitted means are ``a + b r``.

Over every placement (:func:`ecr_surface`) ECR needs, per reference bin, the count, the weight sum ``W_j`` and the
weighted value sum ``S_j`` of the captured pixels over it: three FFT correlations of captured planes with each bin's
indicator plane (:mod:`enmi_torch.placement`).

Convention:
    Captured values are used as they are (not clipped: a value beyond the range is still evidence); reference values
    are hard-binned into ``bins`` equal bins over ``value_range``, clipped into the edge bins.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from enmi_torch.binning import bin_width, hard_bin_index
from enmi_torch.histogram import prepare_inputs
from enmi_torch.placement.fft import Correlator
from enmi_torch.placement.inputs import Surface, SurfaceInputs, check_inputs
from enmi_torch.placement.planes import moment_blocks, per_sample_reference_planes
from enmi_torch.scores.base import Score, reduce_loss
from enmi_torch.scores.shrunk_response import bin_positions, shrunk_llr, shrunk_llr_terms
from enmi_torch.utils.budget import check_surface_memory
from enmi_torch.utils.checks import (
    check_bins,
    check_floating,
    check_option,
    check_value_range,
    check_variance_given,
    fitted_to,
)


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


RESPONSES = ("shrunk", "binned", "linear")
MISFITS = ("independent", "correlated")
MODEL_VARIANCE_ESTIMATE = "estimate"
RESPONSE_VARIANCE_ESTIMATE = "estimate"
# misfit="correlated" sums the residuals' autocovariance over lags up to this fraction of the image's smaller side.
MISFIT_REACH = 1 / 8
# Bins of the cheap first pass whose best placement a surface's estimated tau^2 is read at (the two-stage search's).
FIRST_PASS_BINS = 4
# Fisher scoring stops when tau^2 moves by less than this fraction, or after this many steps (it takes a few).
_FISHER_TOLERANCE, _FISHER_STEPS = 1e-10, 32


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


def check_model_variance(model_variance, bins: int, value_range: tuple[float, float]) -> float | str:
    """``model_variance`` checked: ``"estimate"``, a number >= 0 as a float, ``None`` as its default_model_variance."""
    if model_variance is None:
        return default_model_variance(bins, value_range)
    if model_variance == MODEL_VARIANCE_ESTIMATE:
        return MODEL_VARIANCE_ESTIMATE
    if isinstance(model_variance, bool) or not isinstance(model_variance, (int, float)) or not model_variance >= 0:
        raise ValueError(f"model_variance must be 'estimate', a number >= 0 or None, got {model_variance!r}")
    if model_variance == float("inf"):
        raise ValueError("model_variance must be finite, got inf")
    return float(model_variance)


class _OccupiedBins:
    """The bins that rows ``(S, N)`` of bin indices occupy, labelled once: sums per bin cost ``O(N)``, not ``O(bins)``.

    ``label`` ``(S, N)`` numbers each row's occupied bins apart from every other row's, ``row`` ``(L,)`` is the row of
    each label and ``bin`` ``(L,)`` its bin.
    """

    def __init__(self, cells: Tensor, bins: int) -> None:
        rows = torch.arange(cells.shape[0], device=cells.device)[:, None]
        labels, label = torch.unique(cells + bins * rows, return_inverse=True)
        self.label, self.row, self.bin, self.rows = label, labels // bins, labels % bins, cells.shape[0]

    def sums(self, values: Tensor) -> Tensor:
        """Sums of ``values`` ``(S, N)`` per label, ``(L,)``."""
        return values.new_zeros(self.row.shape[0]).index_add_(0, self.label.flatten(), values.flatten())

    def per_row(self, values: Tensor) -> Tensor:
        """Sums of per-label ``values`` ``(L,)`` over each row's labels, ``(S,)``."""
        return values.new_zeros(self.rows).index_add_(0, self.row, values)


def _binned_fit(cells: Tensor, bins: int):
    """The weighted fit of one mean per reference bin ``cells`` ``(S, N)``, for :func:`_reml_model_variance`."""
    occupied_bins = _OccupiedBins(cells, bins)

    def fit(values: Tensor, weight: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        weight_sums = occupied_bins.sums(weight)
        occupied = weight_sums > 0
        safe = torch.where(occupied, weight_sums, 1.0)
        residual = values - (occupied_bins.sums(weight * values) / safe)[occupied_bins.label]
        trace = occupied_bins.per_row(torch.where(occupied, occupied_bins.sums(weight.square()) / safe, 0.0))
        return residual, trace, occupied_bins.per_row(occupied.long())

    return fit


def _affine_fit(reference: Tensor):
    """The weighted fit of ``a + b r`` on the reference values ``r`` ``(S, N)``, for :func:`_reml_model_variance`."""

    def fit(values: Tensor, weight: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        total = weight.sum(1, keepdim=True).clamp_min(torch.finfo(weight.dtype).tiny)
        # Centred on its weighted mean the reference is orthogonal to the constant: X'WX is diagonal.
        centred = reference - (weight * reference).sum(1, keepdim=True) / total
        spread = (weight * centred.square()).sum(1, keepdim=True)
        sloped = spread > 64 * torch.finfo(weight.dtype).eps * (weight * reference.square()).sum(1, keepdim=True)
        safe = torch.where(sloped, spread, 1.0)
        slope = torch.where(sloped, (weight * centred * values).sum(1, keepdim=True) / safe, 0.0)
        residual = values - (weight * values).sum(1, keepdim=True) / total - slope * centred
        squared = weight.square()
        trace = (
            squared.sum(1) / total[:, 0]
            + torch.where(sloped, (squared * centred.square()).sum(1, keepdim=True) / safe, 0.0)[:, 0]
        )
        return residual, trace, 1 + sloped[:, 0].long()

    return fit


def _reml_model_variance(values: Tensor, noise: Tensor, valid: Tensor, fit, floor: float) -> Tensor:
    """REML ``tau^2`` ``(S,)`` of ``S`` rows of ``N`` pixels (float64): Fisher scoring, at least ``floor``.

    ``values``, ``noise`` (``sigma_n^2``) and ``valid`` (bool) are ``(S, N)``; ``fit(values, weight)`` gives the
    residuals about the weighted fit, ``tr((X' W X)^-1 X' W^2 X)`` and the number of fitted parameters, ``(S,)``
    each. A row with no more valid pixels than fitted parameters gives ``floor``.
    """
    mask = valid.to(values.dtype)
    count = mask.sum(1)
    residual, _, fitted = fit(values, mask)
    moment = (mask * residual.square()).sum(1) / (count - fitted).clamp_min(1)
    tau2 = (moment - (mask * noise).sum(1) / count.clamp_min(1)).clamp_min(floor)
    for _ in range(_FISHER_STEPS):
        weight = mask / (noise + tau2[:, None])
        residual, trace, _ = fit(values, weight)
        squared = weight.square()
        score = 0.5 * ((squared * residual.square()).sum(1) - weight.sum(1) + trace)
        information = 0.5 * squared.sum(1).clamp_min(torch.finfo(values.dtype).tiny)
        updated = (tau2 + score / information).clamp_min(floor)
        settled = bool(((updated - tau2).abs() <= _FISHER_TOLERANCE * updated).all())
        tau2 = updated
        if settled:
            break
    return torch.where(count > fitted, tau2, floor)


def misfit_extent(residual: Tensor, valid: Tensor, misfit_variance: Tensor) -> Tensor:
    """Pixels per independent misfit ``(S,)``: ``1 + sum_{h != 0} taper(h) C(h) / tau^2``, at least 1.

    ``residual`` ``(S, H, W)`` are the captured values less their fitted means, ``valid`` ``(S, H, W)`` bool, and
    ``misfit_variance`` ``(S,)`` the misfit's per-pixel variance ``tau^2``. ``C(h)`` is the residuals' autocovariance
    at lag ``h`` (over the valid pairs at that lag), summed over lags up to ``R = max(1, round(MISFIT_REACH * min(H,
    W)))`` on each axis with the Bartlett taper ``(1 - |dy| / (R + 1)) (1 - |dx| / (R + 1))``. The sensor noise is
    white, so it adds to ``C(0)`` only: the sum is the misfit's. An independent misfit gives about 1; one that is one
    value over blocks of ``b x b`` pixels (``b <= R``) gives ``(1 + 2 sum_{d=1}^{b-1} (1 - d / b) (1 - d / (R + 1)))^2``
    of the block's ``b^2`` (the taper's share: 11.9 of 16 for ``b = 4``, ``R = 8``). At most the valid pixels.

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> blocks = torch.randn(1, 16, 16, generator=generator, dtype=torch.float64)
        >>> misfit = blocks.repeat_interleave(4, 1).repeat_interleave(4, 2)  # one value per 4 x 4 block
        >>> valid = torch.ones(1, 64, 64, dtype=torch.bool)
        >>> noise = 0.5 * torch.randn(1, 64, 64, generator=generator, dtype=torch.float64)
        >>> independent = torch.randn(1, 64, 64, generator=generator, dtype=torch.float64)
        >>> tau2 = torch.ones(1, dtype=torch.float64)
        >>> misfit_extent(misfit + noise, valid, tau2).round(), misfit_extent(independent, valid, tau2).round()
        (tensor([12.], dtype=torch.float64), tensor([1.], dtype=torch.float64))
    """
    _, height, width = residual.shape
    reach = max(1, round(MISFIT_REACH * min(height, width)))
    reach_y, reach_x = min(reach, height - 1), min(reach, width - 1)
    mask = valid.to(residual.dtype)
    count = mask.sum((1, 2))
    residual = torch.where(valid, residual, 0.0)  # an invalid pixel may hold NaN
    centred = torch.where(valid, residual - residual.sum((1, 2), keepdim=True) / count.clamp_min(1)[:, None, None], 0.0)
    size = (2 * height, 2 * width)  # zero padding: no wrap-around

    def lagged_sums(values: Tensor) -> Tensor:
        spectrum = torch.fft.rfft2(values, s=size)
        return torch.fft.irfft2(spectrum * spectrum.conj(), s=size)

    products, pairs = lagged_sums(centred), lagged_sums(mask).round()
    rows = torch.arange(-reach_y, reach_y + 1, device=residual.device)
    cols = torch.arange(-reach_x, reach_x + 1, device=residual.device)
    index = (rows % size[0])[:, None], (cols % size[1])[None, :]
    products, pairs = products[:, index[0], index[1]], pairs[:, index[0], index[1]]
    covariance = torch.where(pairs > 0, products / pairs.clamp_min(1), 0.0)
    taper_y = 1 - rows.to(residual.dtype).abs() / (reach + 1)
    taper = taper_y[:, None] * (1 - cols.to(residual.dtype).abs() / (reach + 1))
    taper[reach_y, reach_x] = 0.0  # lag 0 holds the noise
    summed = (covariance * taper).sum((1, 2))
    tiny = torch.finfo(residual.dtype).tiny
    extent = 1 + summed / misfit_variance.clamp_min(tiny)
    return torch.minimum(extent.clamp_min(1.0), count.clamp_min(1))


def _estimated_model_variance(
    captured: Tensor,
    reference: Tensor,
    noise: Tensor,
    valid: Tensor,
    bins: int,
    value_range: tuple[float, float],
    response: str,
    image_shape: tuple[int, int] | None = None,
) -> Tensor:
    """REML ``tau^2`` ``(S,)`` float64 of ``S`` aligned pairs ``(S, N)``: values, reference, ``sigma^2``, bool valid.

    ``image_shape``: ``(H, W)`` of the ``N = H W`` pixels for ``misfit="correlated"`` (the floor ``bin_width^2 / 12``
    plus the estimate's excess over it times :func:`misfit_extent` of the residuals); ``None`` for an independent
    misfit.
    """
    with torch.no_grad():
        values, reference, noise = (part.detach().to(torch.float64) for part in (captured, reference, noise))
        # Centred values keep the sums of squares free of cancellation; the residuals do not depend on it.
        values = values - (values * valid).sum(1, keepdim=True) / valid.sum(1, keepdim=True).clamp_min(1)
        if response == "linear":
            fit = _affine_fit(torch.where(valid, reference, 0.0))
        else:
            fit = _binned_fit(hard_bin_index(reference, bins, value_range), bins)
        floor = default_model_variance(bins, value_range)
        tau2 = _reml_model_variance(values, noise, valid, fit, floor)
        if image_shape is None:
            return tau2
        residual, _, _ = fit(values, valid / (noise + tau2[:, None]))
        shape = (-1, *image_shape)
        # The quantisation floor stays per pixel, as in the independent model; the misfit beyond it is correlated.
        return floor + (tau2 - floor) * misfit_extent(residual.view(shape), valid.view(shape), tau2)


def _aligned_model_variance(inputs, response: str, image_shape: tuple[int, int] | None = None) -> Tensor:
    """The estimated ``tau^2`` ``(C, B)`` of :func:`ecr`'s checked inputs, one per candidate and sample.

    ``image_shape``: the captured images' ``(H, W)`` for a correlated misfit, ``None`` for an independent one.
    """
    tau2 = _estimated_model_variance(*_flat_pairs(inputs), inputs.bins, inputs.value_range, response, image_shape)
    return tau2.view(inputs.reference.shape[:-1])


def _flat_pairs(inputs) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`ecr`'s checked inputs as ``C B`` rows of ``N`` pixels: captured, reference, variance and bool valid."""
    shape = inputs.reference.shape
    valid = torch.ones(shape, dtype=torch.bool, device=inputs.captured.device)
    if inputs.valid is not None:
        valid = valid & inputs.valid
    parts = (inputs.captured, inputs.reference, inputs.variance, valid)
    return tuple(part.expand(shape).reshape(-1, shape[-1]) for part in parts)


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
        surface = _ecr_surface(part, tau2, FIRST_PASS_BINS, value_range, exact_counts=False)
        half = 0.5 * part.captured_valid.sum((-2, -1)).to(surface.overlap.dtype)
        needed = torch.minimum(half, surface.overlap.amax((-2, -1))).clamp_min(1)[:, None, None]
        scores.append(torch.where(surface.overlap >= needed - 0.5, surface.score, -math.inf))
    return torch.cat(scores)


def _variances_at_peaks(
    inputs: SurfaceInputs,
    scores: Tensor,
    bins: int,
    value_range: tuple[float, float],
    response: str,
    misfit: str,
    model_variance: float | str = MODEL_VARIANCE_ESTIMATE,
) -> tuple[Tensor, Tensor]:
    """``tau^2`` and ``delta^2`` ``(B,)`` float64 at each captured image's best placement in ``scores`` ``(B, Sy, Sx)``.

    ``tau^2``: the estimate there (``model_variance="estimate"``) or the fixed number; a captured image without a
    finite score gets the floor, ``bin_width^2 / 12``, with either misfit. ``delta^2``: the shrunk response's
    (:func:`_estimated_response_variance`) with that ``tau^2``; 0 without a finite score.
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
    image_shape = (height, width) if misfit == "correlated" else None
    if model_variance == MODEL_VARIANCE_ESTIMATE:
        tau2 = _estimated_model_variance(*flat, bins, value_range, response, image_shape)
    else:
        tau2 = torch.full((batch,), float(model_variance), dtype=torch.float64, device=device)
    return tau2, _estimated_response_variance(*flat, tau2, bins, value_range)


def _estimated_response_variance(
    captured: Tensor,
    reference: Tensor,
    noise: Tensor,
    valid: Tensor,
    tau2: Tensor,
    bins: int,
    value_range: tuple[float, float],
) -> Tensor:
    """The shrunk response's ``delta^2`` ``(S,)`` float64 of ``S`` aligned pairs ``(S, N)``: its profile's maximum.

    ``noise`` is ``sigma^2``, ``valid`` bool, ``tau2`` ``(S,)`` the score's model variance. A pair without a valid
    pixel gets 0.
    """
    with torch.no_grad():
        values = torch.where(valid, captured.detach().to(torch.float64), 0.0)  # an invalid pixel may hold NaN
        noise = torch.where(valid, noise.detach().to(torch.float64), 1.0)
        cells = hard_bin_index(torch.where(valid, reference.detach(), value_range[0]), bins, value_range)
        weight = valid / (noise + tau2.to(torch.float64)[:, None])
        centre = (weight * values).sum(1, keepdim=True) / weight.sum(1, keepdim=True).clamp_min(1e-300)
        # Each row's occupied bins, numbered 0, 1, ... in its column of a (most occupied, S) layout: O(N), any bins.
        occupied = _OccupiedBins(cells, bins)
        counts = torch.bincount(occupied.row, minlength=occupied.rows)
        rank = torch.arange(occupied.row.shape[0], device=values.device) - (counts.cumsum(0) - counts)[occupied.row]
        layout = (int(counts.max()), occupied.rows)
        place = (rank, occupied.row)
        weight_sums = values.new_zeros(layout).index_put_(place, occupied.sums(weight))
        value_sums = values.new_zeros(layout).index_put_(place, occupied.sums(weight * (values - centre)))
        positions = values.new_zeros(layout).index_put_(
            place, bin_positions(bins, torch.float64, values.device)[occupied.bin]
        )
        return shrunk_llr(weight_sums, value_sums, positions, value_range)[1]


def _aligned_response_variance(inputs, tau2) -> Tensor:
    """The shrunk response's estimated ``delta^2`` ``(C, B)`` of :func:`ecr`'s checked inputs, ``tau2`` ``(C, B)``."""
    shape = inputs.reference.shape[:-1]
    tau2 = torch.as_tensor(tau2, dtype=torch.float64, device=inputs.captured.device).expand(shape).reshape(-1)
    delta2 = _estimated_response_variance(*_flat_pairs(inputs), tau2, inputs.bins, inputs.value_range)
    return delta2.view(shape)


def _surface_model_variance(
    inputs: SurfaceInputs,
    model_variance,
    bins: int,
    value_range: tuple[float, float],
    response: str,
    misfit: str = "independent",
) -> float | Tensor:
    """A surface's ``tau^2``: the fixed number, or the estimate per captured image ``(B, 1, 1)`` (compute dtype)."""
    return _surface_variances(inputs, model_variance, None, bins, value_range, response, misfit)[0]


def _surface_variances(
    inputs: SurfaceInputs,
    model_variance,
    response_variance,
    bins: int,
    value_range: tuple[float, float],
    response: str,
    misfit: str = "independent",
) -> tuple[float | Tensor, float | Tensor | None]:
    """A surface's ``tau^2`` and ``delta^2``: each the fixed number or the estimate per captured image ``(B, 1, 1)``.

    Both estimates are read at the best placement of one cheap first pass; ``delta^2`` is ``None`` unless the
    response is shrunk and ``response_variance`` given (it is then checked).
    """
    tau2 = check_model_variance(model_variance, bins, value_range)
    shrunk = response == "shrunk" and response_variance is not None
    delta2 = check_response_variance(response_variance) if shrunk else None
    if tau2 != MODEL_VARIANCE_ESTIMATE and delta2 != RESPONSE_VARIANCE_ESTIMATE:
        return tau2, delta2
    tau2_at, delta2_at = _variances_at_peaks(inputs, _first_pass(inputs), bins, value_range, response, misfit, tau2)
    dtype = inputs.captured.dtype
    if tau2 == MODEL_VARIANCE_ESTIMATE:
        tau2 = tau2_at.to(dtype)[:, None, None]
    if delta2 == RESPONSE_VARIANCE_ESTIMATE:
        delta2 = delta2_at.to(dtype)[:, None, None]
    return tau2, delta2


def check_response_variance(response_variance) -> float | str:
    """``response_variance`` checked: ``"estimate"``, or a finite number >= 0 as a float."""
    if response_variance == RESPONSE_VARIANCE_ESTIMATE:
        return RESPONSE_VARIANCE_ESTIMATE
    if (
        isinstance(response_variance, bool)
        or not isinstance(response_variance, (int, float))
        or not 0 <= response_variance < math.inf
    ):
        raise ValueError(f"response_variance must be 'estimate' or a finite number >= 0, got {response_variance!r}")
    return float(response_variance)


def ecr_from_bin_sums(
    sums: BinSums,
    *,
    response: str = "shrunk",
    value_range: tuple[float, float] = (0.0, 256.0),
    response_variance: float | str | Tensor = "estimate",
) -> Tensor:
    """ECR from per-bin sums ``(..., bins)`` (summed over batches or processes if need be), ``(...)``.

    Bins with no valid pixel are left out (``0 / 0``); a placement without any valid pixel scores 0. ``response``:
    ``"shrunk"`` (the default, as :func:`ecr`'s) or ``"binned"``; ``value_range``: the bins' range (the scale of the
    shrunk response's ``delta^2`` grid; the binned response does not use it); ``response_variance``: the shrunk
    response's ``delta^2``, ``"estimate"`` (each set of sums its own, where its profile is largest, held fixed in the
    gradient; the pixels taken as independent) or a number (or a tensor broadcastable to ``(...)``).

    Example:
        >>> sums = BinSums(torch.tensor([[2.0, 2.0]]), torch.tensor([[2.0, 2.0]]), torch.tensor([[-4.0, 4.0]]))
        >>> ecr_from_bin_sums(sums, response="binned")  # (16 / 2 + 16 / 2 - 0) / 2 = 8 nats, less 1 / 2, over 4 pixels
        tensor([1.8750])
        >>> ecr_from_bin_sums(sums, value_range=(0.0, 2.0))  # two bins: the line through them fits, no deviation
        tensor([1.8750])
    """
    check_option("response", response, RESPONSES[:2])
    if not isinstance(response_variance, Tensor):
        response_variance = check_response_variance(response_variance)
    positions = bin_positions(sums.weight.shape[-1], sums.weight.dtype, sums.weight.device)
    shrunk = None if response == "binned" else (positions, value_range, response_variance)
    return _ecr_from_sums(sums.count, sums.weight, sums.weighted_value, -1, shrunk=shrunk)


def _ecr_from_sums(
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


def _aligned_inputs(captured, reference, variance, bins, value_range, model_variance, valid_mask, response, misfit):
    """The checked inputs of :func:`ecr` and :func:`ecr_model_variance`, the model variance option checked, and more.

    The last of the three is the captured images' ``(H, W)`` for a correlated misfit (``None`` for an independent one).
    """
    check_variance_given(variance)
    check_floating("captured", captured)
    inputs = prepare_inputs(
        captured, reference, bins, value_range, variance, valid_mask, "mass", "hard", None, "variance", False
    )
    tau2 = check_model_variance(model_variance, inputs.bins, inputs.value_range)
    check_option("response", response, RESPONSES)
    check_option("misfit", misfit, MISFITS)
    # Flat samples (B, 1, N) are images of one row; a 2-D captured was refused above.
    image_shape = tuple(captured.shape[-2:]) if misfit == "correlated" else None
    return inputs, tau2, image_shape


def _surface_inputs(
    captured, reference, variance, bins, value_range, model_variance, captured_mask, reference_mask, response, misfit
):
    """The checked inputs, bins and value range of :func:`ecr_surface` and :func:`ecr_surface_model_variance`."""
    check_variance_given(variance)
    bins = check_bins(bins)
    value_range = check_value_range(value_range)
    check_model_variance(model_variance, bins, value_range)
    check_option("response", response, RESPONSES)
    check_option("misfit", misfit, MISFITS)
    binned = None if response == "linear" else bins  # the map is binned: refuse one that all falls in one bin
    inputs = check_inputs(
        captured, reference, captured_mask, reference_mask, value_range, variance, reference_bins=binned
    )
    check_surface_memory(inputs.captured, inputs.reference, bins)
    return inputs, bins, value_range


def ecr(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    model_variance: float | str | None = "estimate",
    valid_mask: Tensor | None = None,
    response: str = "shrunk",
    misfit: str = "independent",
    response_variance: float | str = "estimate",
) -> Tensor:
    """Enhanced correlation ratio: the noise-aware Gaussian log-likelihood ratio per valid pixel, in nats, ``(B,)``.

    Args:
        captured: noisy image ``(B, 1, H, W)`` or ``(B, H, W)``, or flat samples ``(B, 1, N)``, floating point.
        reference: noiseless map section, same shape; or ``(C, *captured.shape)``, ``C`` candidates per image.
        variance: per-pixel noise variance of ``captured`` (> 0 where valid): a number, ``(H, W)``,
            ``(1, 1, H, W)`` or ``(B, 1, H, W)``.
        bins: number of equal-width bins the reference is cut into, over ``value_range``.
        value_range: ``(low, high)`` of the reference bins.
        model_variance: ``tau^2 >= 0`` added to every pixel's variance (see the module docstring); ``"estimate"``
            (the default): estimated from each pair at this alignment (:func:`ecr_model_variance`); ``None`` for
            ``bin_width^2 / 12`` (the default before the estimate).
        valid_mask: bool, broadcast like ``variance``; ``False`` pixels are left out (they may hold NaN).
        response: the sensor's response to the map: ``"shrunk"`` (the default: one mean per reference bin, shrunk
            toward an increasing line by as much as the data allow, :mod:`~enmi_torch.scores.shrunk_response`; a
            near-linear pair scores as the line, a non-monotonic one as the bins), ``"binned"`` (one free mean per
            reference bin: any function, monotonic or not) or ``"linear"`` (``a + b r`` with ``b > 0``, the reference
            values themselves: the noise-aware form of normalised cross-correlation, with a penalty of one degree
            of freedom; ``bins`` only check that the reference is resolved).
        misfit: how an estimated ``tau^2`` treats the misfit's spatial correlation: ``"independent"`` (the
            default: pixel by pixel) or ``"correlated"`` (its excess over ``bin_width^2 / 12`` times the pixels per
            independent misfit, :func:`misfit_extent` of the residuals: see the module docstring; captured must be
            images). A fixed ``model_variance`` is used as it is.
        response_variance: the shrunk response's ``delta^2``, how far the bin means may leave the line:
            ``"estimate"`` (the default: each pair its own, where its profile likelihood is largest, held fixed in
            the gradient; see :mod:`~enmi_torch.scores.shrunk_response`) or a number >= 0 (``0``: the line on the
            bin centres). The other responses do not use it.

    Returns:
        ECR ``(B,)`` (``(C, B)`` for candidates), same dtype as ``captured``: larger the better the reference bins
        predict the captured values, small for unrelated images (0 on average for pure noise); ``ECR * n`` is the
        log-likelihood ratio less its mean for pure noise.

    Convention:
        Differentiable in ``captured`` and ``variance`` (the reference is hard-binned; an estimated ``tau^2`` is held
        fixed).

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 16, 16, generator=generator) * 256
        >>> captured = reference + 8 * torch.randn(1, 1, 16, 16, generator=generator)
        >>> ecr(captured, torch.stack([reference, reference.roll(1, -1)]), 64.0, bins=8)
        tensor([[1.7019e+01],
                [5.4228e-05]])
    """
    inputs, tau2, image_shape = _aligned_inputs(
        captured, reference, variance, bins, value_range, model_variance, valid_mask, response, misfit
    )
    if tau2 == MODEL_VARIANCE_ESTIMATE:
        tau2 = _aligned_model_variance(inputs, response, image_shape)[..., None]
    # The sums run in float64 whatever the input: weights 1 / sigma^2 of float32 variances reach 1e45 and squared
    # weighted values of float32 values overflow float32 (NaN from inf - inf); they are a few sums per pixel.
    captured, reference, noise = (
        part.to(torch.float64) for part in (inputs.captured, inputs.reference, inputs.variance)
    )
    total_variance = noise + tau2
    valid = None if inputs.pair_weight is None else inputs.pair_weight.to(torch.float64)
    if response == "linear":
        score = _linear_ecr(captured, reference, total_variance, valid)
    else:
        sums = bin_sums(captured, reference, total_variance, valid, inputs.bins, inputs.value_range)
        delta2 = check_response_variance(response_variance)
        if response == "shrunk" and delta2 == RESPONSE_VARIANCE_ESTIMATE:
            delta2 = _aligned_response_variance(inputs, tau2[..., 0] if isinstance(tau2, Tensor) else tau2)
        score = ecr_from_bin_sums(sums, response=response, value_range=inputs.value_range, response_variance=delta2)
    remedy = "the noise variance is too small for the values' spread in this dtype; pass captured in float64"
    return fitted_to("ecr", score if inputs.with_candidates else score[0], inputs.out_dtype, remedy)


def ecr_model_variance(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    model_variance: float | str | None = "estimate",
    valid_mask: Tensor | None = None,
    response: str = "shrunk",
    misfit: str = "independent",
) -> Tensor:
    """The model variance ``tau^2`` :func:`ecr` adds with these arguments, ``(B,)`` (``(C, B)`` for candidates).

    ``"estimate"``: the REML estimate of each pair at its alignment (see the module docstring); a number or ``None``:
    that number (``bin_width^2 / 12``) for every pair. Arguments as :func:`ecr`'s; float64, without gradient.

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(2, 1, 128, 128, generator=generator, dtype=torch.float64) * 256
        >>> noise, misfit = torch.randn(2, 2, 1, 128, 128, generator=generator, dtype=torch.float64)
        >>> captured = reference + 10 * noise + 20 * misfit  # sigma^2 = 100, tau^2 = 400
        >>> ecr_model_variance(captured, reference, 100.0, bins=64).round()
        tensor([403., 411.], dtype=torch.float64)
    """
    inputs, tau2, image_shape = _aligned_inputs(
        captured, reference, variance, bins, value_range, model_variance, valid_mask, response, misfit
    )
    if tau2 == MODEL_VARIANCE_ESTIMATE:
        tau2 = _aligned_model_variance(inputs, response, image_shape)
    else:
        tau2 = torch.full(inputs.reference.shape[:-1], tau2, dtype=torch.float64, device=inputs.captured.device)
    return tau2 if inputs.with_candidates else tau2[0]


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


def ecr_surface(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    model_variance: float | str | None = "estimate",
    captured_mask: Tensor | None = None,
    reference_mask: Tensor | None = None,
    response: str = "shrunk",
    misfit: str = "independent",
    response_variance: float | str = "estimate",
) -> Surface:
    """ECR (:func:`ecr`) of ``captured`` at every placement inside ``reference``, by FFT.

    Per placement ECR needs, per reference bin ``j``, the count, the weight sum ``W_j`` and the weighted value sum
    ``S_j`` of the captured pixels over it: three correlations of captured planes (valid mask, weights, weighted values)
    with each bin's indicator plane, ``3 K`` inverse FFTs instead of ENMI's ``K^2`` (the
    counts rounded to exact integers).

    Args:
        captured: noisy captured image ``(B, 1, h, w)``, floating point.
        reference: noiseless map section ``(1 or B, 1, Hw, Ww)`` holding every placement, ``Hw >= h``, ``Ww >= w``.
        variance: per-pixel noise variance of ``captured`` (> 0 where valid): a number, ``(h, w)``, ``(1, 1, h, w)``
            or ``(B, 1, h, w)``.
        bins: number of equal-width reference bins over ``value_range``.
        value_range: ``(low, high)``; reference values outside are clipped into the edge bins.
        model_variance: ``tau^2`` (see :func:`ecr`); ``"estimate"`` (the default): one per captured image,
            estimated at the best placement of a cheap first pass (:func:`ecr_surface_model_variance`); ``None`` for
            ``bin_width^2 / 12``.
        captured_mask: bool, broadcast like ``variance``; ``False`` pixels are left out.
        reference_mask: bool ``(Hw, Ww)``, ``(1, 1, Hw, Ww)`` or one per reference; ``False`` cells are left out.
        response: ``"shrunk"``, ``"binned"`` or ``"linear"`` (see :func:`ecr`; the linear response
            takes nine correlations of captured and reference planes, whatever ``bins``).
        misfit: ``"independent"`` or ``"correlated"`` (see :func:`ecr`): for the estimate at the first pass's peak.
        response_variance: the shrunk response's ``delta^2`` (see :func:`ecr`); ``"estimate"`` (the default): one per
            captured image, the maximum of its profile at the first pass's best placement, with that image's
            ``tau^2``, held at every placement.

    Returns:
        :class:`Surface`; ``score[b, u, v]`` equals
        ``ecr(captured[b], reference[b, :, u:u + h, v:v + w], variance,
        valid_mask=captured_mask & reference_mask[...], model_variance=tau2[b])``, ``tau2`` the fixed number or
        :func:`ecr_surface_model_variance`'s estimate (one for every placement of an image); 0 where nothing
        overlaps.

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 12, 12, generator=generator) * 256
        >>> captured = reference[..., 3:9, 2:8] + 4 * torch.randn(1, 1, 6, 6, generator=generator)
        >>> surface = ecr_surface(captured, reference, 16.0, bins=8)
        >>> surface.score.shape, divmod(int(surface.score.flatten().argmax()), 7)
        (torch.Size([1, 7, 7]), (3, 2))
    """
    inputs, bins, value_range = _surface_inputs(
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
    )
    with torch.no_grad():
        model_variance, delta2 = _surface_variances(
            inputs, model_variance, response_variance, bins, value_range, response, misfit
        )
        if response == "linear":
            return _linear_ecr_surface(inputs, model_variance)
        return _ecr_surface(inputs, model_variance, bins, value_range, response_variance=delta2)


def ecr_surface_model_variance(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    model_variance: float | str | None = "estimate",
    captured_mask: Tensor | None = None,
    reference_mask: Tensor | None = None,
    response: str = "shrunk",
    misfit: str = "independent",
) -> Tensor:
    """The model variance ``tau^2`` :func:`ecr_surface` adds with these arguments, ``(B,)`` float64.

    ``"estimate"``: per captured image, the REML estimate at the best placement of the cheap first pass (see the module
    docstring); a number or ``None``: that number (``bin_width^2 / 12``) for every image. Arguments as
    :func:`ecr_surface`'s.

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 80, 80, generator=generator, dtype=torch.float64) * 256
        >>> noise, misfit = torch.randn(2, 1, 1, 64, 64, generator=generator, dtype=torch.float64)
        >>> captured = reference[..., 5:69, 9:73] + 10 * noise + 20 * misfit  # sigma^2 = 100, tau^2 = 400
        >>> ecr_surface_model_variance(captured, reference, 100.0, bins=64).round()
        tensor([424.], dtype=torch.float64)
    """
    inputs, bins, value_range = _surface_inputs(
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
    )
    with torch.no_grad():
        tau2 = _surface_model_variance(inputs, model_variance, bins, value_range, response, misfit)
    if isinstance(tau2, Tensor):
        return tau2.to(torch.float64).flatten()
    return torch.full((inputs.captured.shape[0],), tau2, dtype=torch.float64, device=inputs.captured.device)


def _ecr_surface(
    inputs: SurfaceInputs,
    model_variance: float | Tensor,
    bins: int,
    value_range: tuple[float, float],
    *,
    exact_counts: bool = True,
    response_variance: float | Tensor | None = None,
) -> Surface:
    """ECR at every placement from the per-bin correlations of the captured count, weight and weighted-value planes.

    ``model_variance``: a number, or one per captured image ``(B, 1, 1)``; ``response_variance``: the shrunk response's
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
        scores.append(_ecr_from_sums(count, sums[0, :present], sums[1, :present], 0, overlap, positions))
        overlaps.append(overlap)
    return Surface(torch.stack(scores), torch.stack(overlaps))


def _linear_ecr_surface(inputs: SurfaceInputs, model_variance: float | Tensor) -> Surface:
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


def ecr_loss(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    valid_mask: Tensor | None = None,
    reduction: str = "mean",
    **options,
) -> Tensor:
    """``-ecr(captured, reference, variance, **options)`` reduced over the batch: ``ECR(**options).loss(...)``.

    ``reduction``: ``"none"`` (``(B,)``), ``"mean"`` or ``"sum"``; ``options``: those of :class:`ECR`.

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> ecr_loss(image, image, 1.0, bins=4), ecr_loss(image, image.mT, 1.0, bins=4)
        (tensor(-5.9688), tensor(0.0078))
    """
    return ECR(**options).loss(captured, reference, variance, valid_mask=valid_mask, reduction=reduction)


class ECR(Score):
    """ECR as an object: :func:`ecr`, :func:`ecr_surface` and :func:`ecr_loss` with its options.

    Args:
        bins: number of equal-width reference bins over ``value_range``.
        value_range: ``(low, high)`` of the reference bins.
        model_variance: ``tau^2 >= 0`` added to every pixel's variance; ``"estimate"`` (the default): estimated from
            the data (per aligned pair; per captured image for a surface: see :mod:`~enmi_torch.scores.ecr`);
            ``None`` for ``bin_width^2 / 12`` (the default before the estimate).
        response: ``"shrunk"`` (the default: bin means shrunk toward an increasing line as far as the data allow),
            ``"binned"`` (one free mean per reference bin, any response) or ``"linear"`` (increasing affine).
        misfit: ``"independent"`` (the default) or ``"correlated"``: an estimated ``tau^2``'s excess over the
            quantisation floor times the pixels per independent misfit (:func:`misfit_extent`; see :func:`ecr`).
        response_variance: the shrunk response's ``delta^2``: ``"estimate"`` (the default: per aligned pair; per
            captured image for a surface, at the first pass's best placement) or a number >= 0 (see :func:`ecr`).

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 16, 16, generator=generator) * 256
        >>> captured = reference + 8 * torch.randn(1, 1, 16, 16, generator=generator)
        >>> score = ECR(bins=8)
        >>> score(captured, reference, 64.0), score.loss(captured, reference, 64.0)
        (tensor([17.0186]), tensor(-17.0186))
    """

    name = "ecr"
    uses_variance = True

    def __init__(
        self,
        *,
        bins: int = 32,
        value_range: tuple[float, float] = (0.0, 256.0),
        model_variance: float | str | None = "estimate",
        response: str = "shrunk",
        misfit: str = "independent",
        response_variance: float | str = "estimate",
    ) -> None:
        bins = check_bins(bins)
        value_range = check_value_range(value_range)
        if model_variance is not None:
            model_variance = check_model_variance(model_variance, bins, value_range)
        check_option("response", response, RESPONSES)
        check_option("misfit", misfit, MISFITS)
        response_variance = check_response_variance(response_variance)
        super().__init__(
            bins=bins,
            value_range=value_range,
            model_variance=model_variance,
            response=response,
            misfit=misfit,
            response_variance=response_variance,
        )

    def _value(self, captured, reference, variance, valid_mask) -> Tensor:
        return ecr(captured, reference, variance, valid_mask=valid_mask, **self._options)

    def _surface(self, captured, reference, variance, captured_mask, reference_mask) -> Surface:
        masks = {"captured_mask": captured_mask, "reference_mask": reference_mask}
        return ecr_surface(captured, reference, variance, **masks, **self._options)

    def _loss(self, captured, reference, variance, valid_mask, reduction) -> Tensor:
        return reduce_loss(-self._value(captured, reference, variance, valid_mask), reduction)

    def model_variance_of(
        self, captured: Tensor, reference: Tensor, variance: Tensor | float, *, valid_mask: Tensor | None = None
    ) -> Tensor:
        """The ``tau^2`` added on aligned pairs, ``(B,)`` or ``(C, B)`` float64: :func:`ecr_model_variance`."""
        return ecr_model_variance(captured, reference, variance, valid_mask=valid_mask, **self._model_variance_options)

    def surface_model_variance(
        self,
        captured: Tensor,
        reference: Tensor,
        variance: Tensor | float,
        *,
        captured_mask: Tensor | None = None,
        reference_mask: Tensor | None = None,
    ) -> Tensor:
        """The ``tau^2`` this score's surface adds, ``(B,)`` float64: :func:`ecr_surface_model_variance`."""
        masks = {"captured_mask": captured_mask, "reference_mask": reference_mask}
        return ecr_surface_model_variance(captured, reference, variance, **masks, **self._model_variance_options)

    def response_variance_of(
        self, captured: Tensor, reference: Tensor, variance: Tensor | float, *, valid_mask: Tensor | None = None
    ) -> Tensor:
        """The shrunk response's ``delta^2`` on aligned pairs, ``(B,)`` or ``(C, B)`` float64 (0 for other responses).

        ``"estimate"``: each pair's, at its alignment, with its ``tau^2`` (see :func:`ecr`); a number: that number.
        """
        options = self._model_variance_options
        inputs, tau2, image_shape = _aligned_inputs(
            captured,
            reference,
            variance,
            *(options[name] for name in ("bins", "value_range", "model_variance")),
            valid_mask,
            self.response,
            self.misfit,
        )
        shape = inputs.reference.shape[:-1]
        device = inputs.captured.device
        if self.response != "shrunk" or self.response_variance != RESPONSE_VARIANCE_ESTIMATE:
            value = self.response_variance if self.response == "shrunk" else 0.0
            delta2 = torch.full(shape, value, dtype=torch.float64, device=device)
        else:
            if tau2 == MODEL_VARIANCE_ESTIMATE:
                tau2 = _aligned_model_variance(inputs, self.response, image_shape)
            delta2 = _aligned_response_variance(inputs, tau2)
        return delta2 if inputs.with_candidates else delta2[0]

    def surface_response_variance(
        self,
        captured: Tensor,
        reference: Tensor,
        variance: Tensor | float,
        *,
        captured_mask: Tensor | None = None,
        reference_mask: Tensor | None = None,
    ) -> Tensor:
        """The shrunk response's ``delta^2`` this score's surface holds, ``(B,)`` float64 (0 for other responses).

        ``"estimate"``: per captured image, the maximum of its profile at the cheap first pass's best placement, with
        that image's ``tau^2`` (see :mod:`~enmi_torch.scores.shrunk_response`); a number: that number.
        """
        options = self._model_variance_options
        inputs, bins, value_range = _surface_inputs(
            captured,
            reference,
            variance,
            *(options[name] for name in ("bins", "value_range", "model_variance")),
            captured_mask,
            reference_mask,
            self.response,
            self.misfit,
        )
        with torch.no_grad():
            _, delta2 = _surface_variances(
                inputs, self.model_variance, self.response_variance, bins, value_range, self.response, self.misfit
            )
        batch = inputs.captured.shape[0]
        device = inputs.captured.device
        return (
            torch.as_tensor(0.0 if delta2 is None else delta2, dtype=torch.float64, device=device)
            .flatten()
            .expand(batch)
            .clone()
        )

    @property
    def _model_variance_options(self) -> dict:
        """The options ``tau^2`` depends on (all but the shrunk response's ``delta^2``)."""
        return {name: value for name, value in self._options.items() if name != "response_variance"}

    def _pair_scorer(self, inputs: SurfaceInputs):
        """:func:`~enmi_torch.scores.direct_surface`'s pair score: ECR with the surface's ``tau^2`` and ``delta^2``."""
        tau2, delta2 = _surface_variances(
            inputs, self.model_variance, self.response_variance, self.bins, self.value_range, self.response, self.misfit
        )
        if not isinstance(tau2, Tensor) and not isinstance(delta2, Tensor):
            return super()._pair_scorer(inputs)
        batch = inputs.captured.shape[0]

        def per_sample(value) -> list:
            return torch.as_tensor(value, dtype=torch.float64).flatten().expand(batch).tolist()

        fixed = {"misfit": "independent"}
        shrinks = [None] * batch if delta2 is None else per_sample(delta2)
        samples = [
            self.replace(model_variance=model, **fixed, **({} if shrink is None else {"response_variance": shrink}))
            for model, shrink in zip(per_sample(tau2), shrinks, strict=True)
        ]

        def pair_score(sample: int, captured: Tensor, section: Tensor, variance: Tensor | None, valid: Tensor):
            return samples[sample](captured, section, variance, valid_mask=valid)[0]

        return pair_score

    def _rough_surface(self, captured, reference, variance, captured_mask, reference_mask) -> Surface:
        """:meth:`surface` with the occupied bins read from the weight sums: the two-stage search's first stage.

        It ranks with free bin means (the binned response) whether the score is binned or shrunk: a cheap stage's few
        bins leave little to shrink. Without masked reference cells the per-bin counts are not correlated (two thirds
        of the correlations): a bin counts as occupied where its weight sum exceeds half the smallest pixel weight (FFT
        round-off can flip a few), and the overlap is the captured pixel count.
        """
        if self.response == "linear":
            raise ValueError(f"the rough ECR surface needs a binned or shrunk response, got {self.response!r}")
        inputs = check_inputs(captured, reference, captured_mask, reference_mask, self.value_range, variance)
        with torch.no_grad():
            tau2 = _surface_model_variance(
                inputs, self.model_variance, self.bins, self.value_range, self.response, self.misfit
            )
            return _ecr_surface(inputs, tau2, self.bins, self.value_range, exact_counts=False)

    def _placement_scores(self, placements: Tensor, *, rotations, window, min_overlap: float, cheap: Tensor) -> Tensor:
        """Exact ECR ``(P,)`` of the rotated captured images at placements ``(P, 3)`` (yaw index, row, column).

        As :func:`ecr_surface` and the search's surfaces score them: weights ``1 / (variance + tau^2)`` over the
        captured valid pixels, values centred on each rotation's weighted mean, ``-inf`` below ``min_overlap`` or for
        a rotation without a valid pixel. ``rotations``: the captured images, variances and masks ``(Y, 1, h, w)``;
        ``window``: the reference window and its mask ``(1, 1, Hw, Ww)``; ``cheap``: the search's cheap surface
        ``(Y, Sy, Sx)`` (``-inf`` below ``min_overlap``): an estimated ``tau^2`` is read at each rotation's best
        placement there (the floor for a rotation without a finite one). Per shift, one matrix
        product of the rotations' count, weight and weighted-value planes with the one-hot reference bins under the
        image (unmapped cells in a bin left out) gives the per-bin sums: several times faster on the CPU than
        scattering every pixel.
        """
        captured, variance, valid = rotations
        reference, reference_valid = window
        dtype = torch.float64 if captured.dtype == torch.float64 else torch.float32
        height, width = captured.shape[2:]
        bins, value_range = self.bins, self.value_range
        tau2 = check_model_variance(self.model_variance, bins, value_range)
        delta2 = self.response_variance if self.response == "shrunk" else None
        yaws, yaw_index = torch.unique(placements[:, 0], return_inverse=True)  # only the rotations rescored
        if MODEL_VARIANCE_ESTIMATE in (tau2, delta2):
            rotated = SurfaceInputs(
                captured[yaws, 0].to(dtype),
                reference[:, 0].to(dtype),
                valid[yaws, 0],
                reference_valid[:, 0],
                variance[yaws, 0].to(dtype),
            )
            tau2_at, delta2_at = _variances_at_peaks(
                rotated, cheap[yaws], bins, value_range, self.response, self.misfit, tau2
            )
            if tau2 == MODEL_VARIANCE_ESTIMATE:
                tau2 = tau2_at.to(dtype)[:, None]
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
        score = ecr_from_bin_sums(BinSums(*sums[..., :bins].unbind(1)), response=self.response, **shrunk)
        needed = min_overlap * valid.sum(1)[yaw_index]
        count = sums[:, 0, :bins].sum(1)
        return torch.where((count >= needed - 0.5) & (needed > 0), score, -math.inf)
