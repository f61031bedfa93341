"""ECR's model variance ``tau^2`` and its shrunk response's ``delta^2``, estimated from the data.

Model (:ref:`model-tau`): ``tau^2`` is what a bin of the map leaves unexplained, at least the quantisation
``bin_width^2 / 12``; ``model_variance="estimate"`` takes the restricted maximum likelihood (REML) estimate by Fisher
scoring, each saturated reading completed by expectation-maximisation (:ref:`model-censored`).

``tau^2`` is the quantisation where the map explains the captured image up to the sensor noise, far more where the
scene changed (shadows, cars, another date, another modality); too small a ``tau^2`` trusts the quiet pixels far more
than the misfit allows. REML (the likelihood of the residuals about the fitted bin means, or about ``a + b r`` with
``response="linear"``) does not take the fitted means for evidence against ``tau^2``. One ``tau^2`` per captured
image is estimated:

* on aligned pairs (:func:`~enmi_torch.scores.ecr.ecr`, :func:`~enmi_torch.scores.ecr.ecr_loss`): at the given
  alignment (each candidate reference its own), without gradient; the score is ECR with that ``tau^2``;
* over every placement (:func:`~enmi_torch.scores.ecr.ecr_surface`): at the best placement of a cheap first pass
  (:mod:`~enmi_torch.scores.ecr_placements`); the surface is ECR with that ``tau^2`` at every placement;
* in the two-stage search: at the best placement of its cheap stage, per yaw.

A changed scene's misfit is spatially correlated: a new building, a shadow or a parked car covers many neighbouring
pixels, and the per-pixel model counts each quiet pixel of such a patch as independent evidence.
``misfit="correlated"`` (:ref:`model-correlated`) counts the misfit beyond the quantisation once per ``m`` pixels,
``m`` the pixels per independent misfit read from the residuals' autocovariance (:func:`misfit_extent`): the model
variance becomes ``q + m (tau^2 - q)``, ``q = bin_width^2 / 12``, and where the misfit outweighs the noise the
log-likelihood ratio is about ``m`` times smaller. ``misfit="regional"`` (:ref:`model-regional`) lets ``tau^2`` vary
over the captured image (:mod:`~enmi_torch.scores.ecr_regional_misfit`): a changed part of the scene gets the misfit
it shows instead of the image's average.

Saturated readings (``saturation``, :mod:`~enmi_torch.scores.censoring`) are censored in the estimate by default.
Read as Gaussian values instead (``saturation=None``), clipped grey levels vary far less than their noise variance
says and bias the estimate low: on other-date photographs with two fifths of the pixels clipped it gave the floor
instead of 240 to 313 (``data_tools/notes/scene_change_remedies.md``).

The shrunk response's ``delta^2`` (:mod:`~enmi_torch.scores.shrunk_response`) is estimated where its profile
likelihood is largest, with the pair's ``tau^2`` (:func:`estimated_response_variance`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from enmi_torch.binning import bin_width, hard_bin_index
from enmi_torch.scores.censoring import truncated_moments
from enmi_torch.scores.ecr_regional_misfit import REGIONAL_STEPS, regional_model_variance
from enmi_torch.scores.shrunk_response import bin_positions, shrunk_llr

MISFITS = ("independent", "correlated", "regional")
MODEL_VARIANCE_ESTIMATE = "estimate"
RESPONSE_VARIANCE_ESTIMATE = "estimate"
# misfit="correlated" sums the residuals' autocovariance over lags up to this fraction of the image's smaller side.
MISFIT_REACH = 1 / 8
# Fisher scoring stops when tau^2 moves by less than this fraction, or after this many steps (it takes a few). With
# saturated readings, expectation-maximisation takes more (each step sees the completed values of the last; Aitken's
# extrapolation every third step), and its fixed point is defined to about 1e-7 of tau^2 (the completed values move
# with it): it stops at a millionth.
_FISHER_TOLERANCE, _FISHER_STEPS = 1e-10, 32
_EM_TOLERANCE, _EM_STEPS = 1e-6, 200


def default_model_variance(bins: int, value_range: tuple[float, float]) -> float:
    """``bin_width^2 / 12``: the variance of an amplitude uniform in one reference bin.

    Example:
        >>> default_model_variance(32, (0.0, 256.0))
        5.333333333333333
    """
    return bin_width(bins, value_range) ** 2 / 12


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


class _OccupiedBins:
    """Rows ``(S, N)`` of bin indices as flat labels into an ``(S, bins)`` table: per-bin sums by one ``index_add``.

    ``label`` ``(S, N)`` is each pixel's cell of the table; a bin no pixel of a row falls in sums to 0.
    """

    def __init__(self, cells: Tensor, bins: int) -> None:
        self.rows, self.bins = cells.shape[0], bins
        self.label = cells + bins * torch.arange(self.rows, device=cells.device)[:, None]

    def sums(self, values: Tensor) -> Tensor:
        """Sums of ``values`` ``(S, N)`` per row and bin, flat ``(S bins,)``."""
        return values.new_zeros(self.rows * self.bins).index_add_(0, self.label.flatten(), values.flatten())

    def per_row(self, values: Tensor) -> Tensor:
        """Sums of per-bin ``values`` ``(S bins,)`` over each row's bins, ``(S,)``."""
        return values.view(self.rows, self.bins).sum(1)


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


def _reml_model_variance(
    values: Tensor, noise: Tensor, valid: Tensor, fit, floor: float, side: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """REML ``tau^2`` ``(S,)`` of ``S`` rows of ``N`` pixels (float64): Fisher scoring, at least ``floor``.

    ``values``, ``noise`` (``sigma_n^2``) and ``valid`` (bool) are ``(S, N)``; ``fit(values, weight)`` gives the
    residuals about the weighted fit, ``tr((X' W X)^-1 X' W^2 X)`` and the number of fitted parameters, ``(S,)``
    each. A row with no more valid pixels than fitted parameters gives ``floor``. ``side`` ``(S, N)`` (``+1`` / ``-1``
    at saturated readings, :mod:`~enmi_torch.scores.censoring`): expectation-maximisation, each step replacing a
    saturated reading by its mean beyond the limit under the current fit and adding its variance there to the squared
    residual. Returns ``tau^2`` and the values the last fit saw (the readings, or their completed values).
    """
    mask = valid.to(values.dtype)
    count = mask.sum(1)
    residual, _, fitted = fit(values, mask)
    moment = (mask * residual.square()).sum(1) / (count - fitted).clamp_min(1)
    tau2 = (moment - (mask * noise).sum(1) / count.clamp_min(1)).clamp_min(floor)
    saturated = None if side is None else ((side != 0) & valid).nonzero(as_tuple=True)
    completed, extra, mean = values, 0.0, values - residual
    if saturated is None:
        for _ in range(_FISHER_STEPS):
            updated = _fisher_step(values, noise, mask, fit, tau2, floor, 0.0)[0]
            settled = bool(((updated - tau2).abs() <= _FISHER_TOLERANCE * updated).all())
            tau2 = updated
            if settled:
                break
        return torch.where(count > fitted, tau2, floor), values
    # Each row stops on its own (a batch gives each row what it gives alone), its completed values with it.
    active, history, kept = torch.ones_like(tau2, dtype=torch.bool), [], values
    for _ in range(_EM_STEPS):
        expected, spread = truncated_moments(
            mean[saturated], (noise + tau2[:, None])[saturated], values[saturated], side[saturated]
        )
        completed = values.index_put(saturated, expected)
        extra = torch.zeros_like(values).index_put(saturated, spread)
        updated, mean = _fisher_step(completed, noise, mask, fit, tau2, floor, extra)
        moving = active & ((updated - tau2).abs() > _EM_TOLERANCE * updated)
        tau2 = torch.where(active, updated, tau2)
        kept = torch.where(active[:, None], completed, kept)
        active = moving
        if not bool(active.any()):
            break
        history.append(tau2)
        if len(history) == 3:
            tau2, history = torch.where(active, _extrapolated(*history, floor), tau2), []
    return torch.where(count > fitted, tau2, floor), kept


def _fisher_step(values, noise, mask, fit, tau2, floor: float, extra) -> tuple[Tensor, Tensor]:
    """One Fisher scoring step of the restricted likelihood from ``tau2`` ``(S,)``, and the fitted means ``(S, N)``.

    ``extra``: each reading's variance beyond what its value shows (a saturated reading's, given the fit), or 0.
    """
    weight = mask / (noise + tau2[:, None])
    residual, trace, _ = fit(values, weight)
    squared = weight.square()
    score = 0.5 * ((squared * (residual.square() + extra)).sum(1) - weight.sum(1) + trace)
    information = 0.5 * squared.sum(1).clamp_min(torch.finfo(values.dtype).tiny)
    return (tau2 + score / information).clamp_min(floor), values - residual


def _extrapolated(first: Tensor, second: Tensor, third: Tensor, floor: float) -> Tensor:
    """Aitken's extrapolation of three steps of a linearly converging sequence (EM's), where it converges steadily.

    A row whose steps change sign or do not shrink keeps its last value.
    """
    step, next_step = second - first, third - second
    steady = (step * next_step > 0) & (next_step.abs() < step.abs())
    ratio = torch.where(steady, next_step / torch.where(steady, step, 1.0), 0.0)
    return torch.where(steady, third + next_step * ratio / (1 - ratio), third).clamp_min(floor)


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


def estimated_model_variance(
    captured: Tensor,
    reference: Tensor,
    noise: Tensor,
    valid: Tensor,
    bins: int,
    value_range: tuple[float, float],
    response: str,
    image_shape: tuple[int, int] | None = None,
    misfit: str | None = None,
    side: Tensor | None = None,
) -> Tensor:
    """REML ``tau^2`` ``(S,)`` float64 of ``S`` aligned pairs ``(S, N)``: values, reference, ``sigma^2``, bool valid.

    ``image_shape``: ``(H, W)`` of the ``N = H W`` pixels, for a correlated or regional misfit. ``misfit``:
    ``"independent"``; ``"correlated"`` (the floor ``bin_width^2 / 12`` plus the estimate's excess over it times
    :func:`misfit_extent` of the residuals); ``"regional"`` (a map ``(S, N)``: the per-pixel ``tau^2(x)`` of
    :func:`~enmi_torch.scores.ecr_regional_misfit.regional_model_variance`, refitted
    :data:`~enmi_torch.scores.ecr_regional_misfit.REGIONAL_STEPS` times); ``None``: correlated with an
    ``image_shape``, independent without. ``side``: ``(S, N)`` ``+1`` / ``-1`` at saturated readings (censored,
    :mod:`~enmi_torch.scores.censoring`; the misfit's spatial steps then read the residuals of the completed values),
    ``None`` or all 0 for none.
    """
    if misfit is None:
        misfit = "independent" if image_shape is None else "correlated"
    with torch.no_grad():
        values, reference, noise = (part.detach().to(torch.float64) for part in (captured, reference, noise))
        # Centred values keep the sums of squares free of cancellation; the residuals do not depend on it.
        values = values - (values * valid).sum(1, keepdim=True) / valid.sum(1, keepdim=True).clamp_min(1)
        if response == "linear":
            fit = _affine_fit(torch.where(valid, reference, 0.0))
        else:
            fit = _binned_fit(hard_bin_index(reference, bins, value_range), bins)
        floor = default_model_variance(bins, value_range)
        if side is not None and not bool((side != 0).any()):
            side = None
        tau2, values = _reml_model_variance(values, noise, valid, fit, floor, side)
        if misfit == "independent":
            return tau2
        shape = (-1, *image_shape)
        if misfit == "regional":
            regional = tau2[:, None].expand(noise.shape)
            for _ in range(REGIONAL_STEPS):
                residual, _, _ = fit(values, valid / (noise + regional))
                pixels = (part.view(shape) for part in (residual, noise, valid))
                regional = regional_model_variance(*pixels, tau2, floor, regional.view(shape)).reshape(noise.shape)
            return regional
        residual, _, _ = fit(values, valid / (noise + tau2[:, None]))
        # The quantisation floor stays per pixel, as in the independent model; the misfit beyond it is correlated.
        return floor + (tau2 - floor) * misfit_extent(residual.view(shape), valid.view(shape), tau2)


def aligned_model_variance(
    inputs,
    response: str,
    image_shape: tuple[int, int] | None = None,
    misfit: str | None = None,
    side: Tensor | None = None,
) -> Tensor:
    """The estimated ``tau^2`` ``(C, B)`` of ECR's checked inputs on aligned pairs, one per candidate and sample.

    ``inputs``: as :func:`~enmi_torch.scores.ecr.ecr` checks them. ``image_shape``: the captured images' ``(H, W)``;
    ``misfit`` and ``side`` (``(C B, N)``) as :func:`estimated_model_variance`'s. A regional misfit gives a map per
    pair, ``(C, B, N)``.
    """
    options = (inputs.bins, inputs.value_range, response, image_shape, misfit, side)
    tau2 = estimated_model_variance(*_flat_pairs(inputs), *options)
    return tau2.view(inputs.reference.shape if misfit == "regional" else inputs.reference.shape[:-1])


def _flat_pairs(inputs) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """ECR's checked inputs on aligned pairs as ``C B`` rows of ``N`` pixels: captured, reference, variance, valid."""
    shape = inputs.reference.shape
    valid = torch.ones(shape, dtype=torch.bool, device=inputs.captured.device)
    if inputs.valid is not None:
        valid = valid & inputs.valid
    parts = (inputs.captured, inputs.reference, inputs.variance, valid)
    return tuple(part.expand(shape).reshape(-1, shape[-1]) for part in parts)


def estimated_response_variance(
    captured: Tensor,
    reference: Tensor,
    noise: Tensor,
    valid: Tensor,
    tau2: Tensor,
    bins: int,
    value_range: tuple[float, float],
) -> Tensor:
    """The shrunk response's ``delta^2`` ``(S,)`` float64 of ``S`` aligned pairs ``(S, N)``: its profile's maximum.

    ``noise`` is ``sigma^2``, ``valid`` bool, ``tau2`` ``(S,)`` the score's model variance (``(S, N)`` for a
    regional misfit). A pair without a valid pixel gets 0.
    """
    with torch.no_grad():
        values = torch.where(valid, captured.detach().to(torch.float64), 0.0)  # an invalid pixel may hold NaN
        noise = torch.where(valid, noise.detach().to(torch.float64), 1.0)
        cells = hard_bin_index(torch.where(valid, reference.detach(), value_range[0]), bins, value_range)
        tau2 = tau2.to(torch.float64)
        weight = valid / (noise + (tau2 if tau2.dim() == 2 else tau2[:, None]))
        centre = (weight * values).sum(1, keepdim=True) / weight.sum(1, keepdim=True).clamp_min(1e-300)
        occupied = _OccupiedBins(cells, bins)
        weight_sums = occupied.sums(weight).view(-1, bins).T  # (bins, S): an empty bin weighs 0 and is left out
        value_sums = occupied.sums(weight * (values - centre)).view(-1, bins).T
        positions = bin_positions(bins, torch.float64, values.device)
        return shrunk_llr(weight_sums, value_sums, positions, value_range)[1]


def aligned_response_variance(inputs, tau2) -> Tensor:
    """The shrunk response's estimated ``delta^2`` ``(C, B)`` of ECR's checked inputs on aligned pairs.

    ``inputs``: as :func:`~enmi_torch.scores.ecr.ecr` checks them; ``tau2``: ``(C, B)``, a regional map
    ``(C, B, N)`` or a number.
    """
    shape = inputs.reference.shape[:-1]
    tau2 = torch.as_tensor(tau2, dtype=torch.float64, device=inputs.captured.device)
    if tau2.dim() == len(inputs.reference.shape):
        tau2 = tau2.expand(inputs.reference.shape).reshape(-1, inputs.reference.shape[-1])
    else:
        tau2 = tau2.expand(shape).reshape(-1)
    delta2 = estimated_response_variance(*_flat_pairs(inputs), tau2, inputs.bins, inputs.value_range)
    return delta2.view(shape)
