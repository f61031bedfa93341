"""Dense score surfaces: ECR, ENMI, NMI or NCC of a captured image at every placement inside a reference, by FFT.

With the map hard-binned, the joint histogram of the captured image placed with its top-left pixel at reference cell
``s`` is

    ``J[i, j](s) = sum_n W[n, i] captured_valid[n] * R_j[n + s]``,   ``R_j = reference_valid * [reference bin == j]``,

the cross-correlation of the captured image's bin-weight plane ``W[:, i]`` (a Gaussian likelihood for ENMI, one-hot
for NMI) with the reference's bin-indicator plane ``R_j``. All ``K x K`` correlations over all placements come from one
batched real FFT of each image's planes, a product per bin pair and a pruned inverse FFT (rows first, cropped to the
placements, then columns); bins whose planes are empty on either side are skipped, and the masks add a plane only
where they leave pixels out (otherwise the marginals are constants and box sums). :func:`direct_surface` is the
reference: one :func:`~enmi_torch.histogram.joint_histogram` per placement.

Convention:
    ``captured`` is ``(B, 1, h, w)``; ``reference`` is ``(1, 1, Hw, Ww)`` (shared) or ``(B, 1, Hw, Ww)``, with
    ``Hw >= h`` and ``Ww >= w``. The surface is ``(B, Hw - h + 1, Ww - w + 1)``: entry ``[b, u, v]`` scores the
    captured image with its top-left pixel on reference cell ``(u, v)`` (row, column). Masked pixels of either image are
    left out of that placement's histogram; ``overlap`` counts the captured pixels that remain. A placement without any
    overlap scores 1 (ENMI, NMI; the value of independent images) or 0 (NCC). Surfaces are computed without
    gradient (a search, not a loss: use :func:`~enmi_torch.information.enmi` to differentiate one placement), in
    float64 for float64 inputs and in float32 otherwise; float32 round-off moves a score by about 1e-6 (3e-7
    measured for a 128 x 128 image over 101 x 101 placements by ``data_tools/bench_localize.py``).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import NamedTuple

import torch
from torch import Tensor

from enmi_torch._budget import check_surface_memory
from enmi_torch._checks import (
    check_bins,
    check_captured_in_reference,
    check_finite_where,
    check_log_prior,
    check_option,
    check_resolved_by_bins,
    check_value_range,
    check_variance_given,
)
from enmi_torch._layout import mask_map, variance_map
from enmi_torch.binning import LIKELIHOOD_WEIGHTS, hard_bin_index, likelihood_weights, reliability_weights
from enmi_torch.correlation_ratio import (
    RESPONSES,
    _ecr_from_sums,
    check_model_variance,
    ecr,
    linear_llr,
)
from enmi_torch.histogram import joint_histogram
from enmi_torch.information import _nmi_from_entropies, nmi_from_joint_histogram

METRICS = ("ecr", "enmi", "mixture", "nmi", "ncc")

# The product of one captured plane with a block of reference planes (whole half spectra) stays near this many complex
# elements (4 MiB in complex64, 16 reference planes for a 128 x 128 image in a 228 x 228 reference): batched enough for
# the FFTs, small enough for the CPU cache.
_BLOCK_ELEMENTS = 1 << 19


class Surface(NamedTuple):
    """A dense score surface and the overlap behind each entry.

    Attributes:
        score: ``(B, Sy, Sx)`` score per placement.
        overlap: ``(B, Sy, Sx)`` number of valid captured pixels that land on valid reference cells (integer-valued).
    """

    score: Tensor
    overlap: Tensor


class _Inputs(NamedTuple):
    captured: Tensor  # (B, h, w), masked pixels set to the low end of the range
    reference: Tensor  # (Bw, Hw, Ww), masked cells set to the low end of the range
    captured_valid: Tensor  # (B, h, w) bool
    reference_valid: Tensor  # (Bw, Hw, Ww) bool
    variance: Tensor | None  # (B, h, w), 1 where masked


def enmi_surface(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    kernel: str = "mass",
    log_prior: Tensor | None = None,
    captured_mask: Tensor | None = None,
    reference_mask: Tensor | None = None,
    reliability: bool = False,
) -> Surface:
    """ENMI of ``captured`` at every placement inside ``reference``, by FFT correlation of bin planes.

    Args:
        captured: noisy captured image ``(B, 1, h, w)``, floating point.
        reference: noiseless map section ``(1 or B, 1, Hw, Ww)`` holding every placement, ``Hw >= h``, ``Ww >= w``.
        variance: per-pixel noise variance of ``captured`` (> 0 where valid): a number, ``(h, w)``, ``(1, 1, h, w)``
            or ``(B, 1, h, w)``.
        bins: number of equal-width bins over ``value_range``.
        value_range: ``(low, high)``; values outside are clipped into the edge bins.
        kernel: ``"mass"``, ``"density"`` or ``"truncated"`` (see :func:`~enmi_torch.information.enmi`).
        log_prior: optional log prior of the amplitudes per bin, ``(bins,)``, ``(1, bins)`` or ``(B, bins)``.
        captured_mask: bool, broadcast like ``variance``; ``False`` pixels are left out.
        reference_mask: bool ``(Hw, Ww)``, ``(1, 1, Hw, Ww)`` or one per reference; ``False`` cells are left out.
        reliability: each captured pixel counts with its reliability (see :func:`~enmi_torch.information.enmi`),
            estimated once per captured image over its valid pixels.

    Returns:
        :class:`Surface` with ``score`` ``(B, Hw - h + 1, Ww - w + 1)``: entry ``[b, u, v]`` equals
        ``enmi(captured[b], reference[b, :, u:u + h, v:v + w], variance,
        valid_mask=captured_mask & reference_mask[...])``
        (with ``reliability``, :func:`direct_surface`'s histogram of the captured image's reliability weights).

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 12, 12, generator=generator) * 256
        >>> captured = reference[..., 3:9, 2:8] + 4 * torch.randn(1, 1, 6, 6, generator=generator)
        >>> surface = enmi_surface(captured, reference, 16.0, bins=8)
        >>> surface.score.shape, divmod(int(surface.score.flatten().argmax()), 7)
        (torch.Size([1, 7, 7]), (3, 2))
    """
    check_option("kernel", kernel, LIKELIHOOD_WEIGHTS)
    check_variance_given(variance)
    bins = check_bins(bins)
    value_range = check_value_range(value_range)
    inputs = _check_inputs(captured, reference, captured_mask, reference_mask, value_range, variance, bins)
    check_surface_memory(inputs.captured, inputs.reference, bins)
    batch = inputs.captured.shape[0]
    if log_prior is not None:
        log_prior = check_log_prior(log_prior, bins, batch).to(inputs.captured.dtype).unsqueeze(1)
    if not isinstance(reliability, bool):
        raise TypeError(f"reliability must be True or False, got {reliability!r}")
    with torch.no_grad():
        plane_weights = likelihood_weights(inputs.captured, inputs.variance, bins, value_range, kernel, log_prior)
        pixel_weight = None
        if reliability:
            pixel_weight = reliability_weights(
                inputs.captured.flatten(1), inputs.variance.flatten(1), inputs.captured_valid.flatten(1)
            ).view_as(inputs.captured)
        return _information_surface(plane_weights, inputs, bins, value_range, pixel_weight)


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
    """ECR (:func:`~enmi_torch.correlation_ratio.ecr`) of ``captured`` at every placement inside ``reference``, by FFT.

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
        model_variance: ``tau^2`` (see :func:`~enmi_torch.correlation_ratio.ecr`); ``None`` for ``bin_width^2 / 12``.
        captured_mask: bool, broadcast like ``variance``; ``False`` pixels are left out.
        reference_mask: bool ``(Hw, Ww)``, ``(1, 1, Hw, Ww)`` or one per reference; ``False`` cells are left out.
        response: ``"binned"`` or ``"linear"`` (see :func:`~enmi_torch.correlation_ratio.ecr`; the linear response
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
    inputs = _check_inputs(captured, reference, captured_mask, reference_mask, value_range, variance)
    check_option("response", response, RESPONSES)
    check_surface_memory(inputs.captured, inputs.reference, bins)
    with torch.no_grad():
        if response == "linear":
            return _linear_ecr_surface(inputs, model_variance)
        return _ecr_surface(inputs, model_variance, bins, value_range)


def nmi_surface(
    captured: Tensor,
    reference: Tensor,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    captured_mask: Tensor | None = None,
    reference_mask: Tensor | None = None,
) -> Surface:
    """Hard-binned NMI of ``captured`` at every placement inside ``reference``, by FFT correlation of bin planes.

    Args:
        captured: captured image ``(B, 1, h, w)``, floating point.
        reference: map section ``(1 or B, 1, Hw, Ww)``, ``Hw >= h``, ``Ww >= w``.
        bins: number of equal-width bins over ``value_range``.
        value_range: ``(low, high)``.
        captured_mask: bool ``(h, w)``, ``(1, 1, h, w)`` or ``(B, 1, h, w)``; ``False`` pixels are left out.
        reference_mask: bool ``(Hw, Ww)``, ``(1, 1, Hw, Ww)`` or one per reference.

    Returns:
        :class:`Surface`; ``score[b, u, v]`` equals ``nmi(captured[b], reference[b, :, u:u + h, v:v + w], ...)``.

    Example:
        >>> reference = torch.arange(64.0).reshape(1, 1, 8, 8) * 4
        >>> round(nmi_surface(reference[..., 2:6, 1:5], reference, bins=64).score[0, 2, 1].item(), 4)
        2.0
    """
    bins = check_bins(bins)
    value_range = check_value_range(value_range)
    inputs = _check_inputs(captured, reference, captured_mask, reference_mask, value_range, bins=bins)
    check_surface_memory(inputs.captured, inputs.reference, bins)
    with torch.no_grad():
        one_hot = torch.nn.functional.one_hot(hard_bin_index(inputs.captured, bins, value_range), bins)
        return _information_surface(one_hot.to(inputs.captured.dtype), inputs, bins, value_range)


def ncc_surface(
    captured: Tensor,
    reference: Tensor,
    *,
    captured_mask: Tensor | None = None,
    reference_mask: Tensor | None = None,
) -> Surface:
    """Normalised cross-correlation (Pearson) of ``captured`` at every placement inside ``reference``, masked, by FFT.

    Args:
        captured: captured image ``(B, 1, h, w)``, floating point.
        reference: map section ``(1 or B, 1, Hw, Ww)``, ``Hw >= h``, ``Ww >= w``.
        captured_mask: bool ``(h, w)``, ``(1, 1, h, w)`` or ``(B, 1, h, w)``; ``False`` pixels are left out.
        reference_mask: bool ``(Hw, Ww)``, ``(1, 1, Hw, Ww)`` or one per reference.

    Returns:
        :class:`Surface`; ``score`` in ``[-1, 1]``, the Pearson correlation over the overlapping valid pixels; 0
        where fewer than two pixels overlap or either side is constant there.

    Example:
        >>> reference = torch.arange(64.0).reshape(1, 1, 8, 8) ** 1.5
        >>> round(ncc_surface(reference[..., 2:6, 1:5], reference).score[0, 2, 1].item(), 4)
        1.0
    """
    inputs = _check_inputs(captured, reference, captured_mask, reference_mask, (0.0, 1.0))
    check_surface_memory(inputs.captured, inputs.reference, None)
    with torch.no_grad():
        return _ncc_surface(inputs)


def direct_surface(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float | None = None,
    *,
    metric: str = "enmi",
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    kernel: str = "mass",
    log_prior: Tensor | None = None,
    model_variance: float | None = None,
    captured_mask: Tensor | None = None,
    reference_mask: Tensor | None = None,
    reliability: bool = False,
    em_steps: int = 0,
    response: str = "binned",
) -> Surface:
    """The reference for the FFT surfaces: a loop over placements, one joint histogram (or Pearson sum) each.

    Slow (one :func:`~enmi_torch.histogram.joint_histogram` per placement and sample); use it on small windows to
    check :func:`ecr_surface`, :func:`enmi_surface`, :func:`nmi_surface` and :func:`ncc_surface`, which take the same
    arguments.

    Args:
        captured: ``(B, 1, h, w)``.
        reference: ``(1 or B, 1, Hw, Ww)``.
        variance: as in :func:`enmi_surface`, for ``metric="ecr"``, ``"enmi"`` and ``"mixture"`` only.
        metric: ``"ecr"``, ``"enmi"``, ``"mixture"``, ``"nmi"`` or ``"ncc"``.
        bins: number of bins (ECR, ENMI, NMI).
        value_range: ``(low, high)`` of the bins (ECR, ENMI, NMI).
        kernel: ``"mass"``, ``"density"`` or ``"truncated"`` (ENMI).
        log_prior: optional log prior per bin (ENMI).
        model_variance: ``tau^2`` (ECR).
        response: ``"binned"`` or ``"linear"`` (ECR).
        reliability: reliability-weighted counts (ENMI), weights from each whole captured image's valid pixels.
        em_steps: EM steps of the mixture score (``metric="mixture"``, every placement scored exactly by
            :func:`~enmi_torch.mixture.direct_mixture_surface`).
        captured_mask: as in :func:`enmi_surface`.
        reference_mask: as in :func:`enmi_surface`.

    Returns:
        :class:`Surface`, as the FFT functions.

    Example:
        >>> reference = torch.arange(64.0).reshape(1, 1, 8, 8) * 4
        >>> direct_surface(reference[..., 2:6, 1:5], reference, metric="nmi", bins=64).score[0, 2, 1]
        tensor(2.)
    """
    check_option("metric", metric, METRICS)
    if (metric in ("ecr", "enmi", "mixture")) != (variance is not None):
        raise ValueError(
            f"variance must be given for metric='ecr', 'enmi' or 'mixture' and only then, got metric={metric!r}"
        )
    if metric == "mixture":
        from enmi_torch.localization.mixture_surface import direct_mixture_surface  # mixture builds on this module

        return direct_mixture_surface(
            captured,
            reference,
            variance,
            bins=bins,
            value_range=value_range,
            em_steps=em_steps,
            captured_mask=captured_mask,
            reference_mask=reference_mask,
        )
    if metric == "ncc":
        value_range = (0.0, 1.0)
    bins = check_bins(bins)
    value_range = check_value_range(value_range)
    binned = bins if metric in ("enmi", "nmi") else None
    inputs = _check_inputs(captured, reference, captured_mask, reference_mask, value_range, variance, binned)
    batch, height, width = inputs.captured.shape
    if log_prior is not None:
        log_prior = check_log_prior(log_prior, bins, batch).reshape(-1, bins)
    rows = inputs.reference.shape[1] - height + 1
    cols = inputs.reference.shape[2] - width + 1
    pixel_weight = None
    if reliability:
        if metric != "enmi":
            raise ValueError(f"reliability is only used by metric='enmi', got metric={metric!r}")
        pixel_weight = reliability_weights(
            inputs.captured.flatten(1), inputs.variance.flatten(1), inputs.captured_valid.flatten(1)
        ).view_as(inputs.captured)
    score = inputs.captured.new_empty(batch, rows, cols)
    overlap = inputs.captured.new_empty(batch, rows, cols)
    for sample in range(batch):
        window_index = sample if inputs.reference.shape[0] > 1 else 0
        for row in range(rows):
            for col in range(cols):
                section = inputs.reference[window_index, row : row + height, col : col + width]
                valid = (
                    inputs.captured_valid[sample]
                    & inputs.reference_valid[window_index, row : row + height, col : col + width]
                )
                count = int(valid.sum())
                overlap[sample, row, col] = count
                values = inputs.captured[sample]
                if metric == "ncc":
                    score[sample, row, col] = _pearson(values[valid], section[valid])
                elif metric == "ecr":
                    score[sample, row, col] = (
                        0.0
                        if count == 0
                        else ecr(
                            values[None, None],
                            section[None, None],
                            inputs.variance[sample][None, None],
                            bins=bins,
                            value_range=value_range,
                            model_variance=model_variance,
                            valid_mask=valid[None, None],
                            response=response,
                        )[0]
                    )
                elif count == 0:
                    score[sample, row, col] = 1.0
                else:
                    counts = joint_histogram(
                        values[None, None],
                        section[None, None],
                        bins=bins,
                        value_range=value_range,
                        captured_variance=None if metric == "nmi" else inputs.variance[sample][None, None],
                        valid_mask=valid[None, None],
                        kernel="hard" if metric == "nmi" else kernel,
                        log_prior=None if log_prior is None else log_prior[min(sample, log_prior.shape[0] - 1)],
                        pixel_weight=None if pixel_weight is None else pixel_weight[sample][None, None],
                    )
                    score[sample, row, col] = nmi_from_joint_histogram(counts)[0]
    return Surface(score, overlap)


def _pearson(captured: Tensor, section: Tensor) -> Tensor:
    if captured.numel() < 2:
        return captured.new_zeros(())
    captured = captured - captured.mean()
    section = section - section.mean()
    denominator = (captured.square().sum() * section.square().sum()).sqrt()
    if denominator == 0:
        return captured.new_zeros(())
    return (captured * section).sum() / denominator


def _check_inputs(
    captured: Tensor,
    reference: Tensor,
    captured_mask: Tensor | None,
    reference_mask: Tensor | None,
    value_range: tuple[float, float],
    variance: Tensor | float | None = None,
    bins: int | None = None,
) -> _Inputs:
    """Shapes, masks and values checked; images as ``(B, h, w)`` and ``(Bw, Hw, Ww)`` in the compute dtype.

    With ``bins`` (the captured image is binned) a captured image whose values all fall in one bin while varying is
    refused.
    """
    batch, height, width = check_captured_in_reference(captured, reference, "Hw, Ww")
    dtype = torch.float64 if captured.dtype == torch.float64 else torch.float32
    local_flat = captured.reshape(batch, -1).to(dtype)
    window_flat = reference.reshape(reference.shape[0], -1).to(dtype)

    captured_valid = _mask("captured_mask", captured_mask, captured)
    reference_valid = _mask("reference_mask", reference_mask, reference)
    check_finite_where("captured", local_flat, captured_valid)
    check_finite_where("reference", window_flat, reference_valid)
    if bins is not None:
        check_resolved_by_bins("captured", local_flat, captured_valid, bins, value_range)
    local_flat = torch.where(captured_valid, local_flat, value_range[0])
    window_flat = torch.where(reference_valid, window_flat, value_range[0])
    variance_flat = None
    if variance is not None:
        variance_flat = variance_map("variance", variance, captured, dtype, captured_valid).reshape(
            batch, height, width
        )
    return _Inputs(
        local_flat.reshape(batch, height, width),
        window_flat.reshape(reference.shape[0], *reference.shape[2:]),
        captured_valid.reshape(batch, height, width),
        reference_valid.reshape(reference.shape[0], *reference.shape[2:]),
        variance_flat,
    )


def _mask(name: str, mask: Tensor | None, like: Tensor) -> Tensor:
    """A bool mask as ``(B, N)`` for ``like``'s batch; all ``True`` when ``None``; raises if a sample selects none."""
    if mask is None:
        return torch.ones(like.shape[0], like[0].numel(), dtype=torch.bool, device=like.device)
    return mask_map(name, mask, like, "captured" if name == "captured_mask" else "reference")


def fft_size(length: int) -> int:
    """The smallest ``2^a 3^b 5^c >= length``: an FFT length pocketfft and cuFFT transform fast.

    Example:
        >>> fft_size(228), fft_size(256), fft_size(101)
        (240, 256, 108)
    """
    best = 1 << max(0, (length - 1).bit_length())
    power5 = 1
    while power5 < best:
        power35 = power5
        while power35 < best:
            size = power35
            while size < length:
                size *= 2
            best = min(best, size)
            power35 *= 3
        power5 *= 5
    return best


class _Correlator:
    """All pairwise cross-correlations of captured planes with reference planes, at the placements only, by FFT.

    Spectra are kept transposed, ``(K, Q, P)`` (column frequencies, then row frequencies), so that the first inverse
    transform runs along contiguous rows (``ifft``); its output, cropped to the row placements, is copied transposed
    into a staging buffer, so that the second (``irfft``, cropped to the column placements) also runs along contiguous
    rows and leaves the placements as ``(rows, cols)`` (faster than transforming along the strided axis, which torch
    copies anyway). The ``1 / (P Q)`` of the inverse transform is folded into the reference spectra and the
    conjugate into the captured spectra, once. Products and inverse transforms run in blocks of reference planes
    small enough for the CPU cache.
    """

    def __init__(self, local_shape: tuple[int, int], window_shape: tuple[int, int]) -> None:
        self.rows = window_shape[0] - local_shape[0] + 1
        self.cols = window_shape[1] - local_shape[1] + 1
        # Circular correlation is exact for these placements once the FFT covers the reference (no wrap-around).
        self.shape = (fft_size(window_shape[0]), fft_size(window_shape[1]))

    def spectra(self, planes: Tensor, *, captured: bool) -> Tensor:
        """Transposed half spectra ``(K, Q, P)`` of planes ``(K, h, w)``, conjugated (captured) or scaled."""
        # One 2-D transform (faster than two 1-D passes with a transposed copy between), then one transposed copy.
        spectrum = torch.fft.rfft2(planes, s=self.shape).transpose(-1, -2).contiguous()
        return spectrum.conj_physical_() if captured else spectrum.mul_(1.0 / (self.shape[0] * self.shape[1]))

    def blocks(self, captured: Tensor, reference: Tensor) -> Iterator[tuple[int, int, Tensor]]:
        """Yield ``(index, start, block)`` over the captured planes and blocks of reference planes.

        ``block[c, u, v] = sum_n captured[index][n] reference[start + c][n + (u, v)]``, ``(c, rows, cols)``;
        ``captured`` and ``reference`` are spectra from :meth:`spectra`. Callers may overwrite the blocks.
        """
        planes, half, length = reference.shape
        per_block = max(1, min(planes, _BLOCK_ELEMENTS // (half * length)))
        per_block = -(-planes // -(-planes // per_block))  # equal blocks: 31 planes as 16 + 15, not 18 + 13
        product = reference.new_empty(per_block, half, length)
        staging = reference.new_empty(per_block, self.rows, half)
        for index in range(captured.shape[0]):
            for start in range(0, planes, per_block):
                count = min(per_block, planes - start)
                torch.mul(captured[index], reference[start : start + count], out=product[:count])
                # No ``out=`` for the transforms: torch computes into a fresh tensor and copies it over.
                rows = torch.fft.ifft(product[:count], dim=-1, norm="forward")
                staging[:count].copy_(rows[..., : self.rows].transpose(-1, -2))
                surface = torch.fft.irfft(staging[:count], n=self.shape[1], dim=-1, norm="forward")
                yield index, start, surface[..., : self.cols]


class _EntropySum:
    """Running ``sum c log c`` over blocks of counts ``(c, rows, cols)``, summed over the blocks' first axis.

    ``scratch`` holds the logs of a block, ``(>= c, rows, cols)``; entropy sums used in turn may share one.
    """

    def __init__(self, scratch: Tensor) -> None:
        self.total = scratch.new_zeros(scratch.shape[1:])
        self._tiny = torch.finfo(scratch.dtype).tiny
        self._scratch = scratch

    def add(self, counts: Tensor) -> None:
        """Add the block's ``c log c`` (FFT round-off below 0 counts as 0); ``counts`` is clamped in place."""
        if counts.shape[0] == 0:
            return
        counts.clamp_min_(self._tiny)
        logs = torch.log(counts, out=self._scratch[: counts.shape[0]])
        self.total += logs.mul_(counts).sum(0)


def _box_sums(planes: Tensor, height: int, width: int) -> Tensor:
    """Sums of 0/1 planes ``(K, H, W)`` over every ``height x width`` box, ``(K, H - height + 1, W - width + 1)``.

    Exact integers: float32 while every partial sum stays below 2^24, float64 beyond. The column sums run over the
    row-summed planes, which are narrower than the reference.
    """
    dtype = torch.float32 if planes.shape[-2] * planes.shape[-1] < 1 << 24 else torch.float64
    cumulative = torch.nn.functional.pad(planes.to(dtype).cumsum(-1), (1, 0))
    cumulative = (cumulative[..., width:] - cumulative[..., :-width]).transpose(-1, -2)
    cumulative = torch.nn.functional.pad(cumulative.cumsum(-1), (1, 0))
    return (cumulative[..., height:] - cumulative[..., :-height]).transpose(-1, -2)


class _ReferencePlanes:
    """The reference's side of the information surfaces, computed once per reference.

    ``spectra`` holds the indicator planes of the bins present in the reference, then the reference mask where it leaves
    cells out (``complete`` is ``False``). :meth:`counts` gives, on demand, the exact number of cells of each present
    bin and of valid cells under a captured image at each placement.
    """

    def __init__(
        self, correlator: _Correlator, window_bins: Tensor, reference_valid: Tensor, bins: int, dtype: torch.dtype
    ) -> None:
        present = torch.bincount(window_bins.flatten(), minlength=bins + 1)[:bins].nonzero()[:, 0]
        planes = window_bins == present[:, None, None]
        self.complete = bool(reference_valid.all())
        if not self.complete:
            planes = torch.cat([planes, reference_valid[None]])
        self.spectra = correlator.spectra(planes.to(dtype), captured=False)
        self.bin_count = present.shape[0]
        self._labels = torch.cat([present, present.new_tensor([bins])])
        self._window_bins = window_bins
        self._counts: Tensor | None = None

    def counts(self, height: int, width: int, dtype: torch.dtype) -> Tensor:
        """``(Kr + 1, rows, cols)``: cells of each present bin, then valid cells, under a ``height x width`` image."""
        if self._counts is None:
            indicators = self._window_bins == self._labels[:, None, None]  # the last plane: masked cells
            counts = _box_sums(indicators, height, width).to(dtype)
            counts[-1] = counts[-1].neg_().add_(height * width)
            self._counts = counts
        return self._counts


def _information_surface(
    plane_weights: Tensor,
    inputs: _Inputs,
    bins: int,
    value_range: tuple[float, float],
    pixel_weight: Tensor | None = None,
) -> Surface:
    """NMI of the joint histograms at every placement, from ``(B, h, w, K)`` captured weights and a hard reference.

    The joint counts are the correlations of the occupied captured planes with the present reference planes; bins
    whose planes are empty are skipped. The marginals and the overlap come from one more plane on each side, the
    captured and the reference masks, where these leave pixels out. Where they do not, the captured marginals are
    constant (each pixel's weights sum to 1 and every placement lies inside the reference), and the reference marginals
    and the overlap are box sums of indicator planes, exact integers. Entropies come from
    ``H = log T - sum(c log c) / T`` with ``T`` the overlap. With ``pixel_weight`` ``(B, h, w)`` (reliability; 0 where
    invalid) each pixel counts with its weight: the weight plane gives the reference marginals and ``T``, the mask
    plane the overlap count.
    A placement whose joint histogram holds all but half a pixel's weight in one cell (a constant overlap, up to
    round-off) scores 1, as the core does for a zero joint entropy.
    """
    batch, height, width = inputs.captured.shape
    windows = inputs.reference.shape[0]
    correlator = _Correlator((height, width), tuple(inputs.reference.shape[1:]))
    dtype = inputs.captured.dtype
    weighted = pixel_weight is not None
    pixel_planes = pixel_weight if weighted else inputs.captured_valid.to(dtype)
    plane_weights = (plane_weights * pixel_planes.unsqueeze(-1)).permute(0, 3, 1, 2)
    window_bins = torch.where(inputs.reference_valid, hard_bin_index(inputs.reference, bins, value_range), bins)
    shape = (correlator.rows, correlator.cols)
    scores, overlaps = [], []
    reference = None
    for sample in range(batch):
        window_index = sample if windows > 1 else 0
        if reference is None or windows > 1:
            reference = _ReferencePlanes(
                correlator, window_bins[window_index], inputs.reference_valid[window_index], bins, dtype
            )
        captured_valid = inputs.captured_valid[sample]
        local_complete = bool(captured_valid.all()) and not weighted
        weights = plane_weights[sample]
        weights = weights[weights.flatten(1).amax(1).nonzero()[:, 0]]
        extra = [] if local_complete else [pixel_planes[sample]] + ([captured_valid.to(dtype)] if weighted else [])
        planes = torch.cat([weights, *(plane[None] for plane in extra)])
        captured = correlator.spectra(planes, captured=True)

        scratch = inputs.captured.new_empty(reference.spectra.shape[0], *shape)
        joint, captured_sum, reference_sum = _EntropySum(scratch), _EntropySum(scratch), _EntropySum(scratch)
        joint_peak = inputs.captured.new_zeros(shape)
        overlap = total = None
        for index, start, block in correlator.blocks(captured, reference.spectra):
            bin_rows = block[: max(0, reference.bin_count - start)]
            mask_row = block[-1:] if start + block.shape[0] > reference.bin_count else block[:0]
            if index < weights.shape[0]:
                if bin_rows.shape[0]:
                    torch.maximum(joint_peak, bin_rows.amax(0), out=joint_peak)
                joint.add(bin_rows)
                captured_sum.add(mask_row)  # this captured bin's marginal: its correlation with the reference mask
            elif index == weights.shape[0]:
                reference_sum.add(bin_rows)  # the reference marginals: the captured weights against each bin plane
                if mask_row.shape[0]:
                    total = mask_row[0].clone()
                    overlap = None if weighted else total.round()
            elif mask_row.shape[0]:
                overlap = mask_row[0].round()  # the valid-pixel count of a weighted histogram
        if reference.complete:
            marginals = weights.sum((-2, -1))
            captured_sum.total += torch.special.xlogy(marginals, marginals).sum()
        if local_complete:
            counts = reference.counts(height, width, dtype)
            reference_sum.total += torch.special.xlogy(counts[:-1], counts[:-1]).sum(0)
            overlap = counts[-1]
        if overlap is None:
            overlap = captured_valid.sum().to(dtype).expand(shape)
        if total is None:
            total = overlap if not weighted else pixel_planes[sample].sum().expand(shape)
        smallest = pixel_planes[sample][pixel_planes[sample] > 0].amin() if weighted else 1.0

        positive = total.clamp_min(torch.finfo(dtype).tiny)
        log_total = positive.log()
        joint_entropy = log_total - joint.total / positive
        captured_entropy = log_total - captured_sum.total / positive
        reference_entropy = log_total - reference_sum.total / positive
        informative = (total - joint_peak > 0.5 * smallest) & (joint_entropy > 0) & (overlap > 0)
        score = _nmi_from_entropies(captured_entropy, reference_entropy, joint_entropy, informative)
        scores.append(score)
        overlaps.append(overlap)
    return Surface(torch.stack(scores), torch.stack(overlaps))


def _moment_blocks(inputs: _Inputs, local_planes: Tensor) -> Iterator[Tensor]:
    """Per sample, the ``(3, 3, rows, cols)`` correlations of three captured planes with three reference planes.

    The captured planes ``(B, 3, h, w)`` meet the reference's valid mask, centred values and their squares at every
    placement: the sums behind NCC and ECR's linear response.
    """
    correlator = _Correlator(tuple(inputs.captured.shape[1:]), tuple(inputs.reference.shape[1:]))
    windows = inputs.reference.shape[0]
    reference_valid = inputs.reference_valid.to(inputs.captured.dtype)
    # Centring on the reference's valid mean keeps the sums small, so the FFT round-off stays relative.
    centred = (inputs.reference - _masked_mean(inputs.reference, reference_valid)) * reference_valid
    spectra = None
    for sample in range(inputs.captured.shape[0]):
        window_index = sample if windows > 1 else 0
        if spectra is None or windows > 1:
            planes = torch.stack([reference_valid[window_index], centred[window_index], centred[window_index].square()])
            spectra = correlator.spectra(planes, captured=False)
        captured = correlator.spectra(local_planes[sample], captured=True)
        block = inputs.captured.new_empty(3, 3, correlator.rows, correlator.cols)
        for index, start, part in correlator.blocks(captured, spectra):
            block[index, start : start + part.shape[0]] = part
        yield block


def _ncc_surface(inputs: _Inputs) -> Surface:
    """Masked Pearson correlation from six correlations of masks, centred images and their squares."""
    eps = torch.finfo(inputs.captured.dtype).eps
    captured_valid = inputs.captured_valid.to(inputs.captured.dtype)
    # Centring on the image's own valid mean keeps the sums small, so the FFT round-off stays relative.
    captured = (inputs.captured - _masked_mean(inputs.captured, captured_valid)) * captured_valid
    scores, overlaps = [], []
    for block in _moment_blocks(inputs, torch.stack([captured_valid, captured, captured.square()], dim=1)):
        count = block[0, 0].round()
        local_sum, window_sum = block[1, 0], block[0, 1]
        local_square, window_square, cross = block[2, 0], block[0, 2], block[1, 1]
        safe_count = count.clamp_min(1)
        covariance = cross - local_sum * window_sum / safe_count
        local_spread = local_square - local_sum.square() / safe_count
        window_spread = window_square - window_sum.square() / safe_count
        # A spread within round-off of its raw second moment means a constant overlap: no correlation defined.
        defined = (count >= 2) & (local_spread > 64 * eps * local_square) & (window_spread > 64 * eps * window_square)
        denominator = torch.where(defined, local_spread * window_spread, 1.0).sqrt()
        scores.append(torch.where(defined, covariance / denominator, 0.0).clamp(-1, 1))
        overlaps.append(count)
    return Surface(torch.stack(scores), torch.stack(overlaps))


def _masked_mean(images: Tensor, valid: Tensor) -> Tensor:
    return ((images * valid).sum((-2, -1)) / valid.sum((-2, -1)).clamp_min(1)).reshape(-1, 1, 1)


def _ecr_surface(
    inputs: _Inputs, model_variance: float, bins: int, value_range: tuple[float, float], *, exact_counts: bool = True
) -> Surface:
    """ECR at every placement from the per-bin correlations of the captured count, weight and weighted-value planes.

    With ``exact_counts=False`` (the two-stage search's cheap stage) and a reference without masked cells the per-bin
    counts are not correlated (two thirds of the correlations): a bin counts as occupied where its weight sum exceeds
    half the smallest pixel weight (FFT round-off can flip a few), and the overlap is the captured pixel count.
    """
    batch, height, width = inputs.captured.shape
    windows = inputs.reference.shape[0]
    correlator = _Correlator((height, width), tuple(inputs.reference.shape[1:]))
    dtype = inputs.captured.dtype
    valid = inputs.captured_valid.to(dtype)
    weight = valid / (inputs.variance + model_variance)
    # Centring on the weighted mean keeps S_j^2 / W_j - S^2 / W free of cancellation; the score does not depend on it.
    centre = (weight * inputs.captured).sum((-2, -1), keepdim=True) / weight.sum((-2, -1), keepdim=True)
    weighted_value = weight * (inputs.captured - centre)
    window_bins = torch.where(inputs.reference_valid, hard_bin_index(inputs.reference, bins, value_range), bins)
    scores, overlaps = [], []
    reference = None
    for sample in range(batch):
        window_index = sample if windows > 1 else 0
        if reference is None or windows > 1:
            reference = _ReferencePlanes(
                correlator, window_bins[window_index], inputs.reference_valid[window_index], bins, dtype
            )
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


def _linear_ecr_surface(inputs: _Inputs, model_variance: float) -> Surface:
    """ECR of the increasing affine response at every placement: weighted sums from correlations of planes."""
    valid = inputs.captured_valid.to(inputs.captured.dtype)
    weight = valid / (inputs.variance + model_variance)
    centre = (weight * inputs.captured).sum((-2, -1), keepdim=True) / weight.sum((-2, -1), keepdim=True)
    planes = torch.stack([weight, weight * (inputs.captured - centre), valid], dim=1)
    scores, overlaps = [], []
    for block in _moment_blocks(inputs, planes):
        count = block[2, 0].round()
        llr = linear_llr(block[0, 0], block[1, 0], block[0, 1], block[0, 2], block[1, 1])
        scores.append(torch.where(count > 0, (llr - 0.5) / count.clamp_min(1), 0.0))
        overlaps.append(count)
    return Surface(torch.stack(scores), torch.stack(overlaps))
