"""ECR, the enhanced (noise-aware) correlation ratio: a Gaussian log-likelihood ratio with per-pixel noise variance.

Model (:ref:`model-ecr`): a captured pixel is the sensor's response to the map plus noise, ``v_n ~ N(mu(r_n),
sigma_n^2 + tau^2)``, against one mean for all pixels; ECR is the maximised log-likelihood ratio less its mean for
pure noise, per valid pixel, in nats. The default response is one mean per reference bin shrunk toward an increasing
line (``response="shrunk"``, :ref:`model-shrunk`); ``"binned"`` frees the bin means, ``"linear"`` fits the line.

``sigma_n^2`` is the pixel's noise variance (analytic or learned), ``tau^2`` the model variance (what a bin of the map
does not explain): by default estimated by REML from the data at the alignment, at least ``bin_width^2 / 12``
(:mod:`~enmi_torch.scores.ecr_model_variance`). Saturated readings are scored as censored by default
(:mod:`~enmi_torch.scores.censoring`). A noisy pixel adds its evidence in proportion to its precision instead of a
full unit of histogram weight (ENMI's); with one variance for all pixels the binned response is the classic
correlation ratio (Pearson; Roche et al. 1998) scaled by the signal-to-noise ratio.

This module holds the score (:func:`ecr`, :func:`ecr_surface`, :func:`ecr_loss`, :class:`ECR`) and the ``tau^2`` they
use (:func:`ecr_model_variance`, :func:`ecr_surface_model_variance`); the per-bin sums are in
:mod:`~enmi_torch.scores.ecr_statistics`, the estimates in :mod:`~enmi_torch.scores.ecr_model_variance`, the censored
readings in :mod:`~enmi_torch.scores.ecr_censored`, the surface and the two-stage search's stages in
:mod:`~enmi_torch.scores.ecr_placements`.

Convention:
    Captured values are used as they are (not clipped: a value beyond the range is still evidence, and a reading at a
    saturation level is censored); reference values are hard-binned into ``bins`` equal bins over ``value_range``,
    clipped into the edge bins.
"""

from __future__ import annotations

import torch
from torch import Tensor

from enmi_torch.histogram import prepare_inputs
from enmi_torch.placement.inputs import Surface, SurfaceInputs
from enmi_torch.scores.base import Score, reduce_loss
from enmi_torch.scores.censoring import check_saturation, saturated_pixels
from enmi_torch.scores.ecr_censored import aligned_censored_ecr, aligned_censored_response_variance
from enmi_torch.scores.ecr_model_variance import (
    MISFITS,
    MODEL_VARIANCE_ESTIMATE,
    RESPONSE_VARIANCE_ESTIMATE,
    aligned_model_variance,
    aligned_response_variance,
    check_model_variance,
    check_response_variance,
    default_model_variance,
    misfit_extent,
)
from enmi_torch.scores.ecr_options import RESPONSES, check_ecr_options, ecr_options_checked
from enmi_torch.scores.ecr_placements import (
    check_surface_inputs,
    ecr_surface_from_inputs,
    linear_ecr_surface_from_inputs,
    scores_with_surface_variances,
    surface_variances,
)
from enmi_torch.scores.ecr_statistics import BinSums, bin_sums, ecr_from_bin_sums, linear_ecr
from enmi_torch.scores.ecr_traits import ECRTraits
from enmi_torch.utils.checks import (
    check_floating,
    check_option,
    check_variance_given,
    fitted_to,
)
from enmi_torch.utils.options import signature_defaults

__all__ = [
    "ECR",
    "MISFITS",
    "RESPONSES",
    "BinSums",
    "bin_sums",
    "default_model_variance",
    "ecr",
    "ecr_from_bin_sums",
    "ecr_loss",
    "ecr_model_variance",
    "ecr_surface",
    "ecr_surface_model_variance",
    "misfit_extent",
]


def _aligned_inputs(
    captured, reference, variance, bins, value_range, model_variance, valid_mask, response, misfit, saturation
):
    """The checked inputs of :func:`ecr` and :func:`ecr_model_variance`, the model variance option checked, and more.

    The third is the captured images' ``(H, W)`` for a correlated or regional misfit (``None`` otherwise), the last
    the saturated readings' sides ``(C B, N)`` float64 (:mod:`~enmi_torch.scores.censoring`), ``None`` without any.
    """
    check_variance_given(variance)
    check_floating("captured", captured)
    inputs = prepare_inputs(
        captured, reference, bins, value_range, variance, valid_mask, "mass", "hard", None, "variance", False
    )
    tau2 = check_model_variance(model_variance, inputs.bins, inputs.value_range)
    check_option("response", response, RESPONSES)
    check_option("misfit", misfit, MISFITS)
    saturation = check_saturation(saturation)
    # Flat samples (B, 1, N) are images of one row; a 2-D captured was refused above.
    image_shape = tuple(captured.shape[-2:]) if misfit != "independent" else None
    readings = inputs.captured.detach().to(torch.float64)
    valid = torch.ones_like(readings, dtype=torch.bool) if inputs.valid is None else inputs.valid.expand_as(readings)
    saturated = saturated_pixels(readings, valid, saturation, inputs.value_range, inputs.bins)
    rows = inputs.reference.shape[0]
    side = saturated.side.expand(rows, *saturated.side.shape).reshape(-1, readings.shape[-1]) if saturated.any else None
    return inputs, tau2, image_shape, side


@ecr_options_checked
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
    saturation: str | tuple[float | None, float | None] | None = "value_range",
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
            ``bin_width^2 / 12``.
        valid_mask: bool, broadcast like ``variance``; ``False`` pixels are left out (they may hold NaN).
        response: the sensor's response to the map: ``"shrunk"`` (the default: one mean per reference bin, shrunk
            toward an increasing line by as much as the data allow, :mod:`~enmi_torch.scores.shrunk_response`; a
            near-linear pair scores as the line, a non-monotonic one as the bins), ``"binned"`` (one free mean per
            reference bin: any function, monotonic or not) or ``"linear"`` (``a + b r`` with ``b > 0``, the reference
            values themselves: the noise-aware form of normalised cross-correlation, with a penalty of one degree
            of freedom; ``bins`` only check that the reference is resolved).
        misfit: how an estimated ``tau^2`` treats the misfit's spatial correlation: ``"independent"`` (the
            default: pixel by pixel) or ``"correlated"`` (its excess over ``bin_width^2 / 12`` times the pixels per
            independent misfit, :func:`~enmi_torch.scores.ecr_model_variance.misfit_extent` of the residuals: see
            :mod:`~enmi_torch.scores.ecr_model_variance`; captured must be images) or ``"regional"`` (a ``tau^2(x)``
            per captured pixel, read from the residuals around it: :mod:`~enmi_torch.scores.ecr_regional_misfit`).
            With a fixed ``model_variance`` (used as it is) any other than ``"independent"`` is refused.
        response_variance: the shrunk response's ``delta^2``, how far the bin means may leave the line:
            ``"estimate"`` (the default: each pair its own, where its profile likelihood is largest, held fixed in
            the gradient; see :mod:`~enmi_torch.scores.shrunk_response`) or a number >= 0 (``0``: the line on the
            bin centres). A number with another response is refused (:data:`~enmi_torch.scores.ecr_options.ECR_RULES`).
        saturation: which readings are saturated, scored as censored (a reading at a limit says only "this far or
            beyond": :mod:`~enmi_torch.scores.censoring`, :mod:`~enmi_torch.scores.ecr_censored`): ``"value_range"``
            (the default: readings at an end of ``value_range``, unless the image reads beyond that end), the sensor's
            ``(low, high)`` levels (``None`` for no level at one end; an 8-bit camera: ``(0, 255)``), or ``None``
            (every reading a Gaussian value). Without a saturated reading the value is the Gaussian model's.

    Returns:
        ECR ``(B,)`` (``(C, B)`` for candidates), same dtype as ``captured``: larger the better the reference bins
        predict the captured values, small for unrelated images (0 on average for pure noise); ``ECR * n`` is the
        log-likelihood ratio less its mean for pure noise.

    Convention:
        Differentiable in ``captured`` and ``variance`` (the reference is hard-binned; an estimated ``tau^2`` is held
        fixed; a saturated reading's gradient is that of its tail probability, which starts at the reading).

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 16, 16, generator=generator) * 256
        >>> captured = reference + 8 * torch.randn(1, 1, 16, 16, generator=generator)
        >>> ecr(captured, torch.stack([reference, reference.roll(1, -1)]), 64.0, bins=8)
        tensor([[1.7019e+01],
                [5.4228e-05]])
    """
    inputs, tau2, image_shape, side = _aligned_inputs(
        captured, reference, variance, bins, value_range, model_variance, valid_mask, response, misfit, saturation
    )
    if tau2 == MODEL_VARIANCE_ESTIMATE:
        tau2 = aligned_model_variance(inputs, response, image_shape, misfit, side)
        tau2 = tau2 if misfit == "regional" else tau2[..., None]
    # The sums run in float64 whatever the input: weights 1 / sigma^2 of float32 variances reach 1e45 and squared
    # weighted values of float32 values overflow float32 (NaN from inf - inf); they are a few sums per pixel.
    captured, reference, noise = (
        part.to(torch.float64) for part in (inputs.captured, inputs.reference, inputs.variance)
    )
    total_variance = noise + tau2
    valid = None if inputs.pair_weight is None else inputs.pair_weight.to(torch.float64)
    if side is not None:
        parts = (captured, reference, total_variance, valid, side)
        score = aligned_censored_ecr(*parts, inputs, response, response_variance)
    elif response == "linear":
        score = linear_ecr(captured, reference, total_variance, valid)
    else:
        sums = bin_sums(captured, reference, total_variance, valid, inputs.bins, inputs.value_range)
        delta2 = check_response_variance(response_variance)
        if response == "shrunk" and delta2 == RESPONSE_VARIANCE_ESTIMATE:
            delta2 = aligned_response_variance(inputs, tau2)
        score = ecr_from_bin_sums(sums, response=response, value_range=inputs.value_range, response_variance=delta2)
    remedy = "the noise variance is too small for the values' spread in this dtype; pass captured in float64"
    return fitted_to("ecr", score if inputs.with_candidates else score[0], inputs.out_dtype, remedy)


@ecr_options_checked
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
    saturation: str | tuple[float | None, float | None] | None = "value_range",
) -> Tensor:
    """The model variance ``tau^2`` :func:`ecr` adds with these arguments, ``(B,)`` (``(C, B)`` for candidates).

    ``"estimate"``: the REML estimate of each pair at its alignment (see the module docstring); a number or ``None``:
    that number (``bin_width^2 / 12``) for every pair. Arguments as :func:`ecr`'s; float64, without gradient. An
    estimate with ``misfit="regional"`` is the map ``tau^2(x)`` over each captured image, ``(B, H, W)``.

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(2, 1, 128, 128, generator=generator, dtype=torch.float64) * 256
        >>> noise, misfit = torch.randn(2, 2, 1, 128, 128, generator=generator, dtype=torch.float64)
        >>> captured = reference + 10 * noise + 20 * misfit  # sigma^2 = 100, tau^2 = 400
        >>> ecr_model_variance(captured, reference, 100.0, bins=64).round()
        tensor([403., 411.], dtype=torch.float64)
    """
    inputs, tau2, image_shape, side = _aligned_inputs(
        captured, reference, variance, bins, value_range, model_variance, valid_mask, response, misfit, saturation
    )
    if tau2 == MODEL_VARIANCE_ESTIMATE:
        tau2 = aligned_model_variance(inputs, response, image_shape, misfit, side)
        tau2 = tau2.unflatten(-1, image_shape) if misfit == "regional" else tau2
    else:
        tau2 = torch.full(inputs.reference.shape[:-1], tau2, dtype=torch.float64, device=inputs.captured.device)
    return tau2 if inputs.with_candidates else tau2[0]


@ecr_options_checked
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
    saturation: str | tuple[float | None, float | None] | None = "value_range",
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
        misfit: ``"independent"``, ``"correlated"`` or ``"regional"`` (see :func:`ecr`): for the estimate at the
            first pass's peak (a regional map in the captured image's coordinates, held at every placement).
        response_variance: the shrunk response's ``delta^2`` (see :func:`ecr`); ``"estimate"`` (the default): one per
            captured image, the maximum of its profile at the first pass's best placement, with that image's
            ``tau^2``, held at every placement.
        saturation: the readings the estimates of ``tau^2`` and ``delta^2`` treat as censored (see :func:`ecr`).
            The placements' sums take every reading as a Gaussian value (a censored term is not a sum over the
            placements); the searches rescore their finalists exactly (:meth:`ECR.finalists`).

    Returns:
        :class:`~enmi_torch.placement.Surface`; ``score[b, u, v]`` equals
        ``ecr(captured[b], reference[b, :, u:u + h, v:v + w], variance,
        valid_mask=captured_mask & reference_mask[...], model_variance=tau2[b], response_variance=delta2[b],
        saturation=None)``, ``tau2`` and ``delta2`` the fixed numbers or the estimates
        (:func:`ecr_surface_model_variance`, :meth:`ECR.surface_response_variance`: one for every placement of an
        image); 0 where nothing overlaps.

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 12, 12, generator=generator) * 256
        >>> captured = reference[..., 3:9, 2:8] + 4 * torch.randn(1, 1, 6, 6, generator=generator)
        >>> surface = ecr_surface(captured, reference, 16.0, bins=8)
        >>> surface.score.shape, divmod(int(surface.score.flatten().argmax()), 7)
        (torch.Size([1, 7, 7]), (3, 2))
    """
    inputs, bins, value_range = check_surface_inputs(
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
        saturation,
    )
    with torch.no_grad():
        model_variance, delta2 = surface_variances(
            inputs, model_variance, response_variance, bins, value_range, response, misfit, saturation
        )
        if response == "linear":
            return linear_ecr_surface_from_inputs(inputs, model_variance)
        return ecr_surface_from_inputs(inputs, model_variance, bins, value_range, response_variance=delta2)


@ecr_options_checked
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
    saturation: str | tuple[float | None, float | None] | None = "value_range",
) -> Tensor:
    """The model variance ``tau^2`` :func:`ecr_surface` adds with these arguments, ``(B,)`` float64.

    ``"estimate"``: per captured image, the REML estimate at the best placement of the cheap first pass (see the module
    docstring); a number or ``None``: that number (``bin_width^2 / 12``) for every image. Arguments as
    :func:`ecr_surface`'s. An estimate with ``misfit="regional"`` is the map ``tau^2(x)`` ``(B, h, w)`` over each
    captured image.

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 80, 80, generator=generator, dtype=torch.float64) * 256
        >>> noise, misfit = torch.randn(2, 1, 1, 64, 64, generator=generator, dtype=torch.float64)
        >>> captured = reference[..., 5:69, 9:73] + 10 * noise + 20 * misfit  # sigma^2 = 100, tau^2 = 400
        >>> ecr_surface_model_variance(captured, reference, 100.0, bins=64).round()
        tensor([424.], dtype=torch.float64)
    """
    inputs, bins, value_range = check_surface_inputs(
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
        saturation,
    )
    with torch.no_grad():
        tau2 = surface_variances(inputs, model_variance, None, bins, value_range, response, misfit, saturation)[0]
    if isinstance(tau2, Tensor):
        return tau2.to(torch.float64) if misfit == "regional" else tau2.to(torch.float64).flatten()
    return torch.full((inputs.captured.shape[0],), tau2, dtype=torch.float64, device=inputs.captured.device)


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


class ECR(ECRTraits, Score):
    """ECR as an object: :func:`ecr`, :func:`ecr_surface` and :func:`ecr_loss` with its options.

    Args:
        bins: number of equal-width reference bins over ``value_range``.
        value_range: ``(low, high)`` of the reference bins.
        model_variance: ``tau^2 >= 0`` added to every pixel's variance; ``"estimate"`` (the default): estimated from
            the data (per aligned pair; per captured image for a surface: see :mod:`~enmi_torch.scores.ecr`);
            ``None`` for ``bin_width^2 / 12``.
        response: ``"shrunk"`` (the default: bin means shrunk toward an increasing line as far as the data allow),
            ``"binned"`` (one free mean per reference bin, any response) or ``"linear"`` (increasing affine).
        misfit: ``"independent"`` (the default), ``"correlated"`` (an estimated ``tau^2``'s excess over the
            quantisation floor times the pixels per independent misfit,
            :func:`~enmi_torch.scores.ecr_model_variance.misfit_extent`) or ``"regional"`` (a ``tau^2(x)`` per
            captured pixel, :mod:`~enmi_torch.scores.ecr_regional_misfit`); see :func:`ecr`. Only with
            ``model_variance="estimate"``: with a fixed one it is refused
            (:data:`~enmi_torch.scores.ecr_options.ECR_RULES` says which options need which).
        response_variance: the shrunk response's ``delta^2``: ``"estimate"`` (the default: per aligned pair; per
            captured image for a surface, at the first pass's best placement) or a number >= 0 (see :func:`ecr`);
            a number with another response is refused.
        saturation: the readings scored as censored: ``"value_range"`` (the default: at an end of the range the
            image does not read beyond), the sensor's ``(low, high)`` levels, or ``None`` (see :func:`ecr`).

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
    trait_holders = frozenset({"least_squares", "two_stage"})

    def __init__(
        self,
        *,
        bins: int = 32,
        value_range: tuple[float, float] = (0.0, 256.0),
        model_variance: float | str | None = "estimate",
        response: str = "shrunk",
        misfit: str = "independent",
        response_variance: float | str = "estimate",
        saturation: str | tuple[float | None, float | None] | None = "value_range",
    ) -> None:
        options = {"bins": bins, "value_range": value_range, "model_variance": model_variance, "response": response}
        options.update(misfit=misfit, response_variance=response_variance, saturation=saturation)
        super().__init__(**check_ecr_options(options, signature_defaults(ECR.__init__)))  # ECR_RULES among them

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
        """The ``tau^2`` added on aligned pairs, ``(B,)`` or ``(C, B)`` float64 (a regional map: ``(..., H, W)``)."""
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
        """The ``tau^2`` this score's surface adds, ``(B,)`` (a regional map: ``(B, h, w)``) float64."""
        masks = {"captured_mask": captured_mask, "reference_mask": reference_mask}
        return ecr_surface_model_variance(captured, reference, variance, **masks, **self._model_variance_options)

    def response_variance_of(
        self, captured: Tensor, reference: Tensor, variance: Tensor | float, *, valid_mask: Tensor | None = None
    ) -> Tensor:
        """The shrunk response's ``delta^2`` on aligned pairs, ``(B,)`` or ``(C, B)`` float64 (0 for other responses).

        ``"estimate"``: each pair's, at its alignment, with its ``tau^2`` (see :func:`ecr`); a number: that number.
        """
        options = (self.bins, self.value_range, self.model_variance, valid_mask, self.response, self.misfit)
        inputs, tau2, image_shape, side = _aligned_inputs(captured, reference, variance, *options, self.saturation)
        shape = inputs.reference.shape[:-1]
        device = inputs.captured.device
        if self.response != "shrunk" or self.response_variance != RESPONSE_VARIANCE_ESTIMATE:
            value = self.response_variance if self.response == "shrunk" else 0.0
            delta2 = torch.full(shape, value, dtype=torch.float64, device=device)
        else:
            if tau2 == MODEL_VARIANCE_ESTIMATE:
                tau2 = aligned_model_variance(inputs, self.response, image_shape, self.misfit, side)
            if side is None:
                delta2 = aligned_response_variance(inputs, tau2)
            else:
                delta2 = aligned_censored_response_variance(inputs, tau2, side)
        return delta2 if inputs.with_candidates else delta2[0]

    def held_fit(
        self, captured: Tensor, reference: Tensor, variance: Tensor | float, *, valid_mask: Tensor | None = None
    ) -> ECR:
        """This ECR with ``tau^2`` and ``delta^2`` estimated on one aligned pair and held fixed (fixed ones kept).

        ``self.replace(model_variance=tau2, response_variance=delta2)`` with this pair's :meth:`model_variance_of` and
        :meth:`response_variance_of` (a fixed ``tau^2`` takes the independent misfit: a number is used as it is). Its
        surface is then ECR of each aligned pair under that one model, every reading a Gaussian value.

        Raises:
            ValueError: for more than one pair, or an estimated regional misfit (a map of ``tau^2``, not one number).

        Example:
            >>> generator = torch.Generator().manual_seed(0)
            >>> reference = torch.rand(1, 1, 16, 16, generator=generator, dtype=torch.float64) * 256
            >>> captured = reference + 8 * torch.randn(1, 1, 16, 16, generator=generator, dtype=torch.float64)
            >>> held = ECR(bins=8).held_fit(captured, reference, 64.0)
            >>> held.model_variance == float(ECR(bins=8).model_variance_of(captured, reference, 64.0)[0])
            True
        """
        self.check_variance(variance)
        if captured.shape[0] != 1 or reference.shape != captured.shape:
            raise ValueError(
                "held_fit needs one aligned pair: captured and reference of one shape with one sample, got "
                f"{tuple(captured.shape)} and {tuple(reference.shape)}"
            )
        changes = {}
        if self.model_variance == MODEL_VARIANCE_ESTIMATE:
            if self.misfit == "regional":
                raise ValueError(
                    "held_fit holds one tau^2, got misfit='regional' (a tau^2 per captured pixel): hold another "
                    "misfit, or re-estimate it on every pair (Tracker: TrackerSettings(noise_model='per_frame'))"
                )
            tau2 = self.model_variance_of(captured, reference, variance, valid_mask=valid_mask)
            changes.update(model_variance=float(tau2[0]), misfit="independent")
        if self.response == "shrunk" and self.response_variance == RESPONSE_VARIANCE_ESTIMATE:
            delta2 = self.response_variance_of(captured, reference, variance, valid_mask=valid_mask)
            changes["response_variance"] = float(delta2[0])
        return self.replace(**changes) if changes else self

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
        options = (self.bins, self.value_range, self.model_variance, captured_mask, reference_mask, self.response)
        inputs, _, _ = check_surface_inputs(captured, reference, variance, *options, self.misfit, self.saturation)
        with torch.no_grad():
            names = ("model_variance", "response_variance", "bins", "value_range", "response", "misfit", "saturation")
            _, delta2 = surface_variances(inputs, *(self._options[name] for name in names))
        delta2 = torch.as_tensor(0.0 if delta2 is None else delta2, dtype=torch.float64, device=inputs.captured.device)
        return delta2.flatten().expand(inputs.captured.shape[0]).clone()

    @property
    def _model_variance_options(self) -> dict:
        """The options ``tau^2`` depends on (all but the shrunk response's ``delta^2``)."""
        return {name: value for name, value in self._options.items() if name != "response_variance"}

    def _pair_scorer(self, inputs: SurfaceInputs):
        """:func:`~enmi_torch.scores.direct_surface`'s pair score: ECR with the surface's ``tau^2`` and ``delta^2``."""
        return scores_with_surface_variances(self, inputs)

    @property
    def traits(self) -> frozenset[str]:
        """``"least_squares"`` (:func:`~enmi_torch.register`), and ``"two_stage"`` for a binned or shrunk response."""
        return frozenset({"least_squares"} if self.response == "linear" else {"least_squares", "two_stage"})

    @property
    def estimates_noise_model(self) -> bool:
        """Whether ``tau^2`` is estimated from each pair, or ``delta^2`` (the shrunk response's)."""
        estimates_delta2 = self.response == "shrunk" and self.response_variance == RESPONSE_VARIANCE_ESTIMATE
        return self.model_variance == MODEL_VARIANCE_ESTIMATE or estimates_delta2

    @property
    def surface_is_exact(self) -> bool:
        """Whether the surface equals ECR on each aligned pair: ``tau^2`` and ``delta^2`` fixed, no reading censored.

        By default the surface holds the model variance and response fitted at its first pass's peak and takes every
        reading as a Gaussian value; a search rescores its finalists with :meth:`finalists`, each fitted anew.
        """
        fixed_response = self.response != "shrunk" or self.response_variance != RESPONSE_VARIANCE_ESTIMATE
        return self.model_variance != MODEL_VARIANCE_ESTIMATE and fixed_response and self.saturation is None
