"""Saturated captured pixels as censored observations: a reading at a sensor's limit says only "this far or beyond".

Model (Tobit, :ref:`model-censored`): a captured pixel is ``x_n ~ N(mu_n, s_n^2)`` (``s_n^2 = sigma_n^2 + tau^2``) read
through a sensor that saturates; a reading ``v_n`` at a lower limit adds ``log Phi((v_n - mu_n) / s_n)`` to the
log-likelihood, one at an upper limit ``log Phi((mu_n - v_n) / s_n)``.

Scored as a Gaussian value instead, a saturated pixel looks less noisy than it is (a pile of pixels on one grey
level), which drives an estimated model variance to its floor and over-trusts it. Which pixels are saturated
(``saturation``, an option of :class:`~enmi_torch.ECR`):

* ``"value_range"`` (the default): an end of ``value_range`` is a saturation level of a captured image unless one
  of the image's valid values lies beyond it (a sensor that clips never reads beyond its limit); the pixels within
  :data:`SATURATION_TOLERANCE` bin widths of such an end are saturated. Values inside the range, and every value of
  an image that reads beyond an end, count as they are, so data that were not clipped score as before;
* ``(low, high)``: the sensor's own levels (``None`` for no level at that end): readings ``<= low`` or ``>= high``
  are saturated (an 8-bit camera: ``(0, 255)``);
* ``None``: no pixel is (every reading is a Gaussian value).

The likelihood is not Gaussian in ``mu``, so the fits expand each saturated pixel's term to second order about the
current fit (:func:`tobit_expansion`: a Gaussian *pseudo-observation* with its own value and weight, a Laplace
approximation that is exact for the other pixels) and iterate to the fit's mode; the model variance is estimated by
expectation-maximisation, the saturated pixels replaced by their moments beyond the limit
(:func:`truncated_moments`). Both reduce to the Gaussian model when no pixel is saturated.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from enmi_torch.utils.checks import check_option

SATURATION_FROM_RANGE = "value_range"
# A reading within this many bin widths of an end of value_range is at that end (0..255.999 in a range 0..256).
SATURATION_TOLERANCE = 1e-3
# Beyond this many standard deviations on the wrong side of a limit, lambda + z is its leading term -1 / z.
_SERIES_FROM = 1e4
_HALF_LOG_TWO_PI = 0.5 * math.log(2 * math.pi)
_SQRT_HALF_PI = math.sqrt(math.pi / 2)


class Saturated(NamedTuple):
    """The saturated pixels of ``(S, N)`` readings: ``side`` ``+1`` (at an upper limit), ``-1`` (lower) or ``0``.

    Attributes:
        side: ``(S, N)`` float ``+1``, ``-1`` or ``0`` in the readings' dtype.
        any: whether any pixel is saturated (a Python bool: the Gaussian path is taken otherwise).
    """

    side: Tensor
    any: bool


def check_saturation(saturation) -> str | tuple[float | None, float | None] | None:
    """``saturation`` checked: ``"value_range"``, ``None`` or ``(low, high)`` with finite numbers or ``None``.

    Example:
        >>> check_saturation((0, 255))
        (0.0, 255.0)
        >>> check_saturation((255, 0))
        Traceback (most recent call last):
        ...
        ValueError: saturation must be (low, high) with low < high (None for no level at that end), got (255, 0)
    """
    if saturation is None or isinstance(saturation, str):
        if saturation is not None:
            check_option("saturation", saturation, (SATURATION_FROM_RANGE,))
        return saturation
    message = (
        f"saturation must be 'value_range', None or (low, high) levels (None for no level at that end), got "
        f"{saturation!r}"
    )
    if not isinstance(saturation, (tuple, list)) or len(saturation) != 2:
        raise ValueError(message)
    levels = []
    for level in saturation:
        if level is None:
            levels.append(None)
            continue
        if isinstance(level, bool) or not isinstance(level, (int, float)) or not math.isfinite(level):
            raise ValueError(message)
        levels.append(float(level))
    low, high = levels
    if low is not None and high is not None and not low < high:
        raise ValueError(
            f"saturation must be (low, high) with low < high (None for no level at that end), got {saturation!r}"
        )
    return (low, high)


def saturated_pixels(
    values: Tensor, valid: Tensor, saturation, value_range: tuple[float, float], bins: int
) -> Saturated:
    """Which of ``(S, N)`` readings are saturated under ``saturation`` (see the module docstring); ``valid`` bool.

    Example:
        >>> values = torch.tensor([[0.0, 3.0, 255.999, 100.0], [-2.0, 0.0, 256.0, 9.0]])
        >>> saturated_pixels(values, values == values, "value_range", (0.0, 256.0), 32).side
        tensor([[-1.,  0.,  1.,  0.],
                [ 0.,  0.,  1.,  0.]])
    """
    side = torch.zeros_like(values)
    if saturation is None:
        return Saturated(side, False)
    if saturation == SATURATION_FROM_RANGE:
        low, high = value_range
        tolerance = SATURATION_TOLERANCE * (high - low) / bins
        large = torch.finfo(values.dtype).max
        lowest = torch.where(valid, values, large).amin(-1, keepdim=True)
        highest = torch.where(valid, values, -large).amax(-1, keepdim=True)
        at_low = valid & (values <= low + tolerance) & (lowest >= low)
        at_high = valid & (values >= high - tolerance) & (highest <= high)
    else:
        low, high = saturation
        at_low = valid & (values <= low) if low is not None else torch.zeros_like(valid)
        at_high = valid & (values >= high) if high is not None else torch.zeros_like(valid)
    side = at_high.to(values.dtype) - at_low.to(values.dtype)
    return Saturated(side, bool((at_low | at_high).any()))


def _mills_terms(z: Tensor) -> tuple[Tensor, Tensor]:
    """``lambda(z) = phi(z) / Phi(z)`` and ``lambda(z) + z`` (> 0), accurate for every ``z``.

    Below 0, ``Phi(z) / phi(z) = sqrt(pi / 2) erfcx(-z / sqrt 2)``, whose reciprocal loses no digits where ``Phi`` would
    underflow; ``lambda + z`` then loses about ``z^2`` ulps to cancellation (1e-13 at ``z = -40``), and beyond
    :data:`_SERIES_FROM` standard deviations it is the leading term ``-1 / z`` (both errors 2e-8 at the switch).
    Above 0, ``exp(log phi(z) - log Phi(z))``.
    """
    negative = z < 0
    below = torch.where(negative, z, -1.0)
    mills_below = (_SQRT_HALF_PI * torch.special.erfcx(-below / math.sqrt(2))).reciprocal()
    above = torch.where(negative, 1.0, z)
    mills_above = torch.exp(-0.5 * above.square() - _HALF_LOG_TWO_PI - torch.special.log_ndtr(above))
    mills = torch.where(negative, mills_below, mills_above)
    excess = torch.where(z < -_SERIES_FROM, -torch.where(z < -_SERIES_FROM, z, -1.0).reciprocal(), mills + z)
    return mills, excess


def _standardised(mean: Tensor, total_variance: Tensor, values: Tensor, side: Tensor):
    """``(s, z, lambda, lambda + z)`` in float64 (the Mills ratio's cancellation needs it), broadcast."""
    mean, total_variance, values, side = (part.to(torch.float64) for part in (mean, total_variance, values, side))
    scale = total_variance.sqrt()
    z = side * (mean - values) / scale
    return (scale, z, *_mills_terms(z))


def tobit_expansion(
    mean: Tensor, total_variance: Tensor, values: Tensor, side: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """A saturated pixel's term expanded to second order in ``mu`` about ``mean``: a Gaussian pseudo-observation.

    ``log Phi(z)``, ``z = side (mean - value) / s``, equals ``constant - weight (pseudo - mu)^2 / 2`` up to third
    order in ``mu - mean``: ``weight = lambda (lambda + z) / s^2`` (``lambda = phi(z) / Phi(z)``), ``pseudo = mean +
    side s / (lambda + z)`` and ``constant = log Phi(z) + lambda / (2 (lambda + z))``. Far on the wrong side of the
    limit the pseudo-observation tends to the reading with weight ``1 / s^2``; deep beyond it, to weight 0. All
    arguments broadcast; ``side`` is ``+1`` or ``-1`` where it matters (its other entries give finite values to
    discard).

    Returns:
        ``(pseudo, weight, constant)`` in the dtype of ``mean`` and ``total_variance`` (computed in float64).

    Example:
        >>> mean, variance = torch.tensor([100.0, 250.0], dtype=torch.float64), torch.tensor(25.0, dtype=torch.float64)
        >>> pseudo, weight, constant = tobit_expansion(mean, variance, torch.tensor(255.0), torch.tensor(1.0))
        >>> pseudo.round(decimals=2).tolist(), (weight * variance).round(decimals=3).tolist()  # far below; near
        ([255.32, 259.52], [0.999, 0.801])
    """
    dtype = torch.promote_types(mean.dtype, total_variance.dtype)
    scale, z, mills, excess = _standardised(mean, total_variance, values, side)
    weight = mills * excess / scale.square()
    pseudo = mean + side * scale / excess
    constant = torch.special.log_ndtr(z) + mills / (2 * excess)
    return pseudo.to(dtype), weight.to(dtype), constant.to(dtype)


def truncated_moments(mean: Tensor, total_variance: Tensor, values: Tensor, side: Tensor) -> tuple[Tensor, Tensor]:
    """Mean and variance of ``x ~ N(mean, s^2)`` given that it lies beyond the reading (``side`` ``+1``: above it).

    ``E = mean + side s lambda(z)``, ``Var = s^2 (1 - lambda(z) (lambda(z) + z))``, ``z = side (mean - value) / s``:
    the expectation step of the model variance's estimate. Arguments broadcast.

    Example:
        >>> mean, variance = torch.tensor(0.0, dtype=torch.float64), torch.tensor(1.0, dtype=torch.float64)
        >>> moments = truncated_moments(mean, variance, torch.tensor(0.0, dtype=torch.float64), torch.tensor(1.0))
        >>> [round(float(moment), 4) for moment in moments]  # the half-normal: sqrt(2 / pi), 1 - 2 / pi
        [0.7979, 0.3634]
    """
    dtype = torch.promote_types(mean.dtype, total_variance.dtype)
    scale, _, mills, excess = _standardised(mean, total_variance, values, side)
    expected = mean + side * scale * mills
    return expected.to(dtype), (scale.square() * (1 - mills * excess).clamp_min(0.0)).to(dtype)
