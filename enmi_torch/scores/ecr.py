"""ECR, the enhanced (noise-aware) correlation ratio: a Gaussian log-likelihood ratio with per-pixel noise variance.

Model: the sensor sees a function of the map, blurred by noise whose variance is known per pixel. A captured pixel
``v_n`` over a reference pixel in bin ``j_n`` is ``v_n ~ N(mu_{j_n}, sigma_n^2 + tau^2)``, one unknown mean per
reference bin (any response, monotonic or not), ``sigma_n^2`` the pixel's noise variance (analytic or learned) and
``tau^2`` the model variance (what a bin of the map does not explain; by default the spread of an amplitude
uniform in a bin, ``bin_width^2 / 12``). The alternative is one mean for all pixels (captured independent of the
map). With weights ``w_n = 1 / (sigma_n^2 + tau^2)`` and per-bin sums ``W_j = sum w_n``, ``S_j = sum w_n v_n``, the
maximised log-likelihood ratio is

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

from enmi_torch._budget import check_surface_memory
from enmi_torch._checks import check_bins, check_floating, check_option, check_value_range, check_variance_given
from enmi_torch.binning import bin_width, hard_bin_index
from enmi_torch.histogram import _prepare
from enmi_torch.placement.fft import Correlator
from enmi_torch.placement.inputs import Surface, SurfaceInputs, check_inputs
from enmi_torch.placement.planes import moment_blocks, per_sample_reference_planes
from enmi_torch.scores.base import REDUCTIONS, Score, reduce_loss


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


RESPONSES = ("binned", "linear")


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


def check_model_variance(model_variance, bins: int, value_range: tuple[float, float]) -> float:
    """``model_variance`` as a float >= 0; ``None`` gives :func:`default_model_variance`."""
    if model_variance is None:
        return default_model_variance(bins, value_range)
    if isinstance(model_variance, bool) or not isinstance(model_variance, (int, float)) or not model_variance >= 0:
        raise ValueError(f"model_variance must be a number >= 0 or None, got {model_variance!r}")
    if model_variance == float("inf"):
        raise ValueError("model_variance must be finite, got inf")
    return float(model_variance)


def ecr_from_bin_sums(sums: BinSums) -> Tensor:
    """ECR from per-bin sums ``(..., bins)`` (summed over batches or processes if need be), ``(...)``.

    Bins with no valid pixel are left out (``0 / 0``); a placement without any valid pixel scores 0.

    Example:
        >>> sums = BinSums(torch.tensor([[2.0, 2.0]]), torch.tensor([[2.0, 2.0]]), torch.tensor([[-4.0, 4.0]]))
        >>> ecr_from_bin_sums(sums)  # (16 / 2 + 16 / 2 - 0) / 2 = 8 nats, minus 1 / 2 for 2 bins, over 4 pixels
        tensor([1.8750])
    """
    return _ecr_from_sums(sums.count, sums.weight, sums.weighted_value, -1)


def _ecr_from_sums(
    count: Tensor, weight: Tensor, weighted_value: Tensor, dim: int, total_count: Tensor | None = None
) -> Tensor:
    """:func:`ecr_from_bin_sums` with the bins along ``dim`` (the score surfaces keep them first).

    ``total_count``: the valid pixels, when ``count`` only marks the occupied bins (``count.sum(dim)`` otherwise).
    """
    occupied = count > 0.5
    safe_weight = torch.where(occupied, weight, 1.0)
    between = torch.where(occupied, weighted_value.square() / safe_weight, 0.0).sum(dim)
    total_weight = weight.sum(dim)
    between = between - weighted_value.sum(dim).square() / total_weight.clamp_min(torch.finfo(between.dtype).tiny)
    if total_count is None:
        total_count = count.sum(dim)
    penalty = (occupied.sum(dim) - 1).clamp_min(0).to(between.dtype)
    return torch.where(total_count > 0.5, 0.5 * (between - penalty) / total_count.clamp_min(1), 0.0)


def ecr(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    model_variance: float | None = None,
    valid_mask: Tensor | None = None,
    response: str = "binned",
) -> Tensor:
    """Enhanced correlation ratio: the noise-aware Gaussian log-likelihood ratio per valid pixel, in nats, ``(B,)``.

    Args:
        captured: noisy image ``(B, 1, H, W)``, ``(B, H, W)`` or ``(B, N)``, floating point.
        reference: noiseless map section, same shape; or ``(C, *captured.shape)``, ``C`` candidates per image.
        variance: per-pixel noise variance of ``captured`` (> 0 where valid): a number, ``(H, W)``,
            ``(1, 1, H, W)`` or ``(B, 1, H, W)``.
        bins: number of equal-width bins the reference is cut into, over ``value_range``.
        value_range: ``(low, high)`` of the reference bins.
        model_variance: ``tau^2 >= 0`` added to every pixel's variance (see the module docstring); ``None`` for
            ``bin_width^2 / 12``.
        valid_mask: bool, broadcast like ``variance``; ``False`` pixels are left out (they may hold NaN).
        response: the sensor's response to the map: ``"binned"`` (one mean per reference bin: any function,
            monotonic or not; the default) or ``"linear"`` (``a + b r`` with ``b > 0``, the reference values
            themselves: the noise-aware form of normalised cross-correlation, with a penalty of one degree of
            freedom; ``bins`` only check that the reference is resolved).

    Returns:
        ECR ``(B,)`` (``(C, B)`` for candidates), same dtype as ``captured``: larger the better the reference bins
        predict the captured values, small for unrelated images (0 on average for pure noise); ``ECR * n`` is the
        log-likelihood ratio less its mean for pure noise.

    Convention:
        Differentiable in ``captured`` and ``variance`` (the reference is hard-binned).

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 16, 16, generator=generator) * 256
        >>> captured = reference + 8 * torch.randn(1, 1, 16, 16, generator=generator)
        >>> ecr(captured, torch.stack([reference, reference.roll(1, -1)]), 64.0, bins=8)
        tensor([[17.4752],
                [ 0.4031]])
    """
    check_variance_given(variance)
    check_floating("captured", captured)
    inputs = _prepare(
        captured, reference, bins, value_range, variance, valid_mask, "mass", "hard", None, "variance", False
    )
    tau2 = check_model_variance(model_variance, inputs.bins, inputs.value_range)
    check_option("response", response, RESPONSES)
    if response == "linear":
        score = _linear_ecr(inputs.captured, inputs.reference, inputs.variance + tau2, inputs.pair_weight)
        return (score if inputs.with_candidates else score[0]).to(inputs.out_dtype)
    sums = bin_sums(
        inputs.captured, inputs.reference, inputs.variance + tau2, inputs.pair_weight, inputs.bins, inputs.value_range
    )
    score = ecr_from_bin_sums(sums)
    return (score if inputs.with_candidates else score[0]).to(inputs.out_dtype)


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
    model_variance: float | None = None,
    captured_mask: Tensor | None = None,
    reference_mask: Tensor | None = None,
    response: str = "binned",
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
        model_variance: ``tau^2`` (see :func:`ecr`); ``None`` for ``bin_width^2 / 12``.
        captured_mask: bool, broadcast like ``variance``; ``False`` pixels are left out.
        reference_mask: bool ``(Hw, Ww)``, ``(1, 1, Hw, Ww)`` or one per reference; ``False`` cells are left out.
        response: ``"binned"`` or ``"linear"`` (see :func:`ecr`; the linear response
            takes nine correlations of captured and reference planes, whatever ``bins``).

    Returns:
        :class:`Surface`; ``score[b, u, v]`` equals
        ``ecr(captured[b], reference[b, :, u:u + h, v:v + w], variance,
        valid_mask=captured_mask & reference_mask[...])``;
        0 where nothing overlaps.

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 12, 12, generator=generator) * 256
        >>> captured = reference[..., 3:9, 2:8] + 4 * torch.randn(1, 1, 6, 6, generator=generator)
        >>> surface = ecr_surface(captured, reference, 16.0, bins=8)
        >>> surface.score.shape, divmod(int(surface.score.flatten().argmax()), 7)
        (torch.Size([1, 7, 7]), (3, 2))
    """
    check_variance_given(variance)
    bins = check_bins(bins)
    value_range = check_value_range(value_range)
    model_variance = check_model_variance(model_variance, bins, value_range)
    binned = None if response == "linear" else bins  # the map is binned: refuse one that all falls in one bin
    inputs = check_inputs(
        captured, reference, captured_mask, reference_mask, value_range, variance, reference_bins=binned
    )
    check_option("response", response, RESPONSES)
    check_surface_memory(inputs.captured, inputs.reference, bins)
    with torch.no_grad():
        if response == "linear":
            return _linear_ecr_surface(inputs, model_variance)
        return _ecr_surface(inputs, model_variance, bins, value_range)


def _ecr_surface(
    inputs: SurfaceInputs,
    model_variance: float,
    bins: int,
    value_range: tuple[float, float],
    *,
    exact_counts: bool = True,
) -> Surface:
    """ECR at every placement from the per-bin correlations of the captured count, weight and weighted-value planes.

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
        scores.append(_ecr_from_sums(count, sums[0, :present], sums[1, :present], 0, overlap))
        overlaps.append(overlap)
    return Surface(torch.stack(scores), torch.stack(overlaps))


def _linear_ecr_surface(inputs: SurfaceInputs, model_variance: float) -> Surface:
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
    captured: Tensor, reference: Tensor, variance: Tensor | float, *, reduction: str = "mean", **options
) -> Tensor:
    """``-ecr(captured, reference, variance, **options)`` reduced over the batch.

    ``reduction``: ``"none"`` (``(B,)``), ``"mean"`` or ``"sum"``; ``options``: the keyword arguments of
    :func:`ecr`.

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> ecr_loss(image, image, 1.0, bins=4), ecr_loss(image, image.mT, 1.0, bins=4)
        (tensor(-7.3843), tensor(-0.3736))
    """
    check_option("reduction", reduction, REDUCTIONS)
    return reduce_loss(-ecr(captured, reference, variance, **options), reduction)


class ECR(Score):
    """ECR as an object: :func:`ecr`, :func:`ecr_surface` and :func:`ecr_loss` with its options.

    Args:
        bins: number of equal-width reference bins over ``value_range``.
        value_range: ``(low, high)`` of the reference bins.
        model_variance: ``tau^2 >= 0`` added to every pixel's variance; ``None`` for ``bin_width^2 / 12``.
        response: ``"binned"`` (one mean per reference bin, any response) or ``"linear"`` (increasing affine).

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 16, 16, generator=generator) * 256
        >>> captured = reference + 8 * torch.randn(1, 1, 16, 16, generator=generator)
        >>> score = ECR(bins=8)
        >>> score(captured, reference, 64.0), score.loss(captured, reference, 64.0)
        (tensor([17.4752]), tensor(-17.4752))
    """

    name = "ecr"
    uses_variance = True

    def __init__(
        self,
        *,
        bins: int = 32,
        value_range: tuple[float, float] = (0.0, 256.0),
        model_variance: float | None = None,
        response: str = "binned",
    ) -> None:
        bins = check_bins(bins)
        value_range = check_value_range(value_range)
        if model_variance is not None:
            model_variance = check_model_variance(model_variance, bins, value_range)
        check_option("response", response, RESPONSES)
        super().__init__(bins=bins, value_range=value_range, model_variance=model_variance, response=response)

    def _value(self, captured, reference, variance, valid_mask) -> Tensor:
        return ecr(captured, reference, variance, valid_mask=valid_mask, **self._options)

    def _surface(self, captured, reference, variance, captured_mask, reference_mask) -> Surface:
        masks = {"captured_mask": captured_mask, "reference_mask": reference_mask}
        return ecr_surface(captured, reference, variance, **masks, **self._options)

    def _loss(self, captured, reference, variance, valid_mask, reduction) -> Tensor:
        return ecr_loss(captured, reference, variance, valid_mask=valid_mask, reduction=reduction, **self._options)

    def _rough_surface(self, captured, reference, variance, captured_mask, reference_mask) -> Surface:
        """:meth:`surface` with the occupied bins read from the weight sums: the two-stage search's first stage.

        Without masked reference cells the per-bin counts are not correlated (two thirds of the correlations): a bin
        counts as occupied where its weight sum exceeds half the smallest pixel weight (FFT round-off can flip a few),
        and the overlap is the captured pixel count.
        """
        if self.response != "binned":
            raise ValueError(f"the rough ECR surface needs response='binned', got {self.response!r}")
        inputs = check_inputs(captured, reference, captured_mask, reference_mask, self.value_range, variance)
        tau2 = check_model_variance(self.model_variance, self.bins, self.value_range)
        with torch.no_grad():
            return _ecr_surface(inputs, tau2, self.bins, self.value_range, exact_counts=False)

    def _placement_scores(self, placements: Tensor, *, rotations, window, min_overlap: float) -> Tensor:
        """Exact ECR ``(P,)`` of the rotated captured images at placements ``(P, 3)`` (yaw index, row, column).

        As :func:`ecr_surface` and the search's surfaces score them: weights ``1 / (variance + tau^2)`` over the
        captured valid pixels, values centred on each rotation's weighted mean, ``-inf`` below ``min_overlap`` or for
        a rotation without a valid pixel. ``rotations``: the captured images, variances and masks ``(Y, 1, h, w)``;
        ``window``: the reference window and its mask ``(1, 1, Hw, Ww)``. Per shift, one matrix product of the
        rotations' count, weight and weighted-value planes with the one-hot reference bins under the image (unmapped
        cells in a bin left out) gives the per-bin sums: several times faster on the CPU than scattering every pixel.
        """
        captured, variance, valid = rotations
        reference, reference_valid = window
        dtype = torch.float64 if captured.dtype == torch.float64 else torch.float32
        height, width = captured.shape[2:]
        bins, value_range = self.bins, self.value_range
        tau2 = check_model_variance(self.model_variance, bins, value_range)
        yaws, yaw_index = torch.unique(placements[:, 0], return_inverse=True)  # only the rotations rescored
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
        score = ecr_from_bin_sums(BinSums(*sums[..., :bins].unbind(1)))
        needed = min_overlap * valid.sum(1)[yaw_index]
        count = sums[:, 0, :bins].sum(1)
        return torch.where((count >= needed - 0.5) & (needed > 0), score, -math.inf)
