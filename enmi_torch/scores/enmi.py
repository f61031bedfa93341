"""ENMI, the enhanced (noise-aware) NMI of the paper: each captured pixel spreads its unit weight over the bins.

Model (:ref:`model-enmi`): a captured pixel ``v`` with noise variance ``sigma^2`` (``N0 / A~`` for a road tile) counts
in captured bin ``i`` with the weight its Gaussian likelihood gives amplitudes in that bin, paired with the hard bin of
the reference pixel under it; ENMI is the Studholme NMI of that joint histogram.

The weights are :func:`~enmi_torch.binning.likelihood_weights`, the NMI
:func:`~enmi_torch.information.nmi_from_joint_histogram`. Over every placement (:func:`enmi_surface`) the joint
histograms come from FFT correlations of the captured likelihood planes with the reference's bin planes
(:func:`~enmi_torch.placement.information.information_surface`, shared with hard NMI).
"""

from __future__ import annotations

import torch
from torch import Tensor

from enmi_torch.binning import LIKELIHOOD_WEIGHTS, PARZEN_KERNELS, likelihood_weights_unchecked, reliability_weights
from enmi_torch.histogram import joint_histogram, joint_histogram_of_inputs, prepare_inputs
from enmi_torch.information import nmi_from_joint_histogram
from enmi_torch.placement.information import information_surface
from enmi_torch.placement.inputs import Surface, SurfaceInputs, check_inputs
from enmi_torch.scores.base import Score, reduce_loss
from enmi_torch.utils.budget import check_surface_memory
from enmi_torch.utils.checks import (
    check_bins,
    check_log_prior,
    check_log_prior_allows_a_bin,
    check_option,
    check_same_device,
    check_value_range,
    check_variance_given,
)


def enmi(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    kernel: str = "mass",
    log_prior: Tensor | None = None,
    reference_kernel: str = "hard",
    valid_mask: Tensor | None = None,
    reliability: bool = False,
) -> Tensor:
    """Enhanced NMI: each captured pixel spreads its unit weight over the bins by its Gaussian likelihood, ``(B,)``.

    A captured pixel ``v`` with noise variance ``sigma^2`` (``sigma^2 = N0 / A`` for a road tile of focal-plane
    area ``A``) counts in captured bin ``i`` with the weight its likelihood gives amplitudes in that bin, paired with
    the reference pixel's bin; ENMI is the Studholme NMI of that joint histogram.

    Args:
        captured: noisy image ``(B, 1, H, W)`` or ``(B, H, W)`` (flat samples: ``(B, 1, N)``), floating point.
        reference: noiseless map section, same shape; or ``(C, *captured.shape)``, ``C`` candidate sections per
            captured image, scored against likelihood weights computed once (the costly part).
        variance: per-pixel noise variance (> 0 where valid): a number, ``(H, W)``, ``(1, 1, H, W)`` or
            ``(B, 1, H, W)``.
        bins: number of equal-width bins over ``value_range``.
        value_range: ``(low, high)``.
        kernel: how a captured pixel's unit spreads over the bins (the name :func:`nmi` uses for its Parzen
            windows): ``"mass"`` (probability of each bin under ``N(v, sigma^2)``, tails in the edge bins),
            ``"density"`` (density at the bin centres, normalised over bins) or ``"truncated"`` (the masses inside the
            range, renormalised).
        log_prior: optional log prior of the amplitude per bin, ``(bins,)`` or ``(B, bins)`` (e.g.
            :func:`~enmi_torch.binning.gaussian_log_prior`): weights become the MAP posterior.
        reference_kernel: ``"hard"`` (noiseless map, default) or ``"triangular"``/``"xu"`` for a reference gradient.
        valid_mask: bool, broadcast like ``variance``; ``False`` pixels are left out.
        reliability: each pixel counts with its reliability ``s^2 / (s^2 + sigma^2)``
            (:func:`~enmi_torch.binning.reliability_weights`) instead of a unit weight, so very noisy pixels weigh
            less in the histogram; with one variance for all pixels the score is unchanged. Uses the dense
            (autograd) histogram path.

    Returns:
        ENMI in ``[1, 2]``, ``(B,)`` (``(C, B)`` for candidates), same dtype as ``captured``; it tends to hard
        :func:`nmi` as the variance tends to 0.

    Raises:
        MemoryBudgetError: when the ``(C, B, bins, bins)`` histograms and their entropies would exceed the memory
            budget (see :func:`~enmi_torch.histogram.joint_histogram`).

    Convention:
        Differentiable in ``captured`` and ``variance`` (and ``reference`` with a soft reference kernel).

    Example:
        >>> generator = torch.Generator().manual_seed(0)
        >>> reference = torch.rand(1, 1, 16, 16, generator=generator) * 256
        >>> captured = reference + 8 * torch.randn(1, 1, 16, 16, generator=generator)
        >>> enmi(captured, reference, 64.0, bins=8)
        tensor([1.5003])
        >>> enmi(captured, reference.roll(1, -1), 64.0, bins=8)
        tensor([1.0179])
        >>> enmi(captured, torch.stack([reference, reference.roll(1, -1)]), 64.0, bins=8)
        tensor([[1.5003],
                [1.0179]])
    """
    check_option("kernel", kernel, LIKELIHOOD_WEIGHTS)
    check_variance_given(variance)
    check_same_device("reference", reference, "captured", captured)
    if isinstance(log_prior, Tensor):
        check_log_prior_allows_a_bin(log_prior)
    if isinstance(variance, Tensor):
        check_same_device("variance", variance, "captured", captured)
    _check_reliability(reliability)
    inputs = prepare_inputs(
        captured, reference, bins, value_range, variance, valid_mask, kernel, reference_kernel, log_prior, "variance"
    )
    if reliability:
        pixel_weight = reliability_weights(inputs.captured, inputs.variance, inputs.valid)
        inputs = inputs._replace(pair_weight=pixel_weight, weighted=True)
    return nmi_from_joint_histogram(joint_histogram_of_inputs(inputs, scored=True))


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
        kernel: ``"mass"``, ``"density"`` or ``"truncated"`` (see :func:`enmi`).
        log_prior: optional log prior of the amplitudes per bin, ``(bins,)``, ``(1, bins)`` or ``(B, bins)``.
        captured_mask: bool, broadcast like ``variance``; ``False`` pixels are left out.
        reference_mask: bool ``(Hw, Ww)``, ``(1, 1, Hw, Ww)`` or one per reference; ``False`` cells are left out.
        reliability: each captured pixel counts with its reliability (see :func:`enmi`),
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
    inputs = check_inputs(captured, reference, captured_mask, reference_mask, value_range, variance, bins)
    check_surface_memory(inputs.captured, inputs.reference, bins)
    batch = inputs.captured.shape[0]
    if log_prior is not None:
        log_prior = check_log_prior(log_prior, bins, batch).to(inputs.captured).unsqueeze(1)
    _check_reliability(reliability)
    with torch.no_grad():
        plane_weights = likelihood_weights_unchecked(
            inputs.captured, inputs.variance, bins, value_range, kernel, log_prior
        )
        pixel_weight = None
        if reliability:
            pixel_weight = reliability_weights(
                inputs.captured.flatten(1), inputs.variance.flatten(1), inputs.captured_valid.flatten(1)
            ).view_as(inputs.captured)
        return information_surface(plane_weights, inputs, bins, value_range, pixel_weight)


def enmi_loss(
    captured: Tensor,
    reference: Tensor,
    variance: Tensor | float,
    *,
    valid_mask: Tensor | None = None,
    reduction: str = "mean",
    **options,
) -> Tensor:
    """``2 - enmi(captured, reference, variance, **options)`` reduced over the batch: ``ENMI(**options).loss(...)``.

    ``reduction``: ``"none"`` (``(B,)``), ``"mean"`` or ``"sum"``; ``options``: those of :class:`ENMI`.

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> enmi_loss(image, image, 1e-6, bins=4), enmi_loss(image, image.mT, 1e-6, bins=4)
        (tensor(0.), tensor(1.))
    """
    return ENMI(**options).loss(captured, reference, variance, valid_mask=valid_mask, reduction=reduction)


class ENMI(Score):
    """ENMI as an object: :func:`enmi`, :func:`enmi_surface` and :func:`enmi_loss` with its options.

    Args:
        bins: number of equal-width bins over ``value_range``.
        value_range: ``(low, high)`` of the bins.
        kernel: ``"mass"``, ``"density"`` or ``"truncated"`` likelihood weights (see :func:`enmi`).
        log_prior: optional log prior of the amplitudes per bin: ``(bins,)`` for every sample or ``(B, bins)``, one
            row per sample of the batches it scores (:meth:`per_sample`).
        reliability: reliability-weighted counts (see :func:`enmi`).
        reference_kernel: ``"hard"`` (the noiseless map; the only one the surface takes), ``"triangular"`` or
            ``"xu"``.

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> score = ENMI(bins=4)
        >>> score(image, image, 1e-6), score(image, image.mT, 1e-6)
        (tensor([2.]), tensor([1.]))
    """

    name = "enmi"
    uses_variance = True
    empty_score = 1.0
    _bins_captured = True

    def __init__(
        self,
        *,
        bins: int = 32,
        value_range: tuple[float, float] = (0.0, 256.0),
        kernel: str = "mass",
        log_prior: Tensor | None = None,
        reliability: bool = False,
        reference_kernel: str = "hard",
    ) -> None:
        bins = check_bins(bins)
        value_range = check_value_range(value_range)
        check_option("kernel", kernel, LIKELIHOOD_WEIGHTS)
        if log_prior is not None:
            # Any number of rows: the batch it meets is checked per call (per_sample, the functions).
            check_log_prior(
                log_prior, bins, log_prior.shape[0] if isinstance(log_prior, Tensor) and log_prior.ndim == 2 else 1
            )
        _check_reliability(reliability)
        check_option("reference_kernel", reference_kernel, PARZEN_KERNELS)
        super().__init__(
            bins=bins,
            value_range=value_range,
            kernel=kernel,
            log_prior=log_prior,
            reliability=reliability,
            reference_kernel=reference_kernel,
        )

    def per_sample(self, batch: int) -> list[Score]:
        """One score per sample: a ``(B, bins)`` ``log_prior`` gives each sample its row (checked against ``batch``)."""
        if self.log_prior is None:
            return [self] * batch
        rows = check_log_prior(self.log_prior, self.bins, batch).reshape(-1, self.bins)
        return [self.replace(log_prior=rows[min(sample, rows.shape[0] - 1)]) for sample in range(batch)]

    def _value(self, captured, reference, variance, valid_mask) -> Tensor:
        return enmi(captured, reference, variance, valid_mask=valid_mask, **self._options)

    def _surface(self, captured, reference, variance, captured_mask, reference_mask) -> Surface:
        if self.reference_kernel != "hard":
            raise ValueError(f"ENMI's surface needs reference_kernel='hard', got {self.reference_kernel!r}")
        options = {name: value for name, value in self._options.items() if name != "reference_kernel"}
        return enmi_surface(
            captured, reference, variance, captured_mask=captured_mask, reference_mask=reference_mask, **options
        )

    def _loss(self, captured, reference, variance, valid_mask, reduction) -> Tensor:
        return reduce_loss(2 - self._value(captured, reference, variance, valid_mask), reduction)

    def _pair_scorer(self, inputs: SurfaceInputs):
        """With ``reliability``, the pixel weights come from each whole captured image, as in :func:`enmi_surface`."""
        if not self.reliability:
            return super()._pair_scorer(inputs)
        weights = reliability_weights(
            inputs.captured.flatten(1), inputs.variance.flatten(1), inputs.captured_valid.flatten(1)
        ).view_as(inputs.captured)
        samples = self.per_sample(inputs.captured.shape[0])

        def pair_score(sample: int, captured: Tensor, section: Tensor, variance: Tensor, valid: Tensor) -> Tensor:
            counts = joint_histogram(
                captured,
                section,
                bins=self.bins,
                value_range=self.value_range,
                captured_variance=variance,
                valid_mask=valid,
                kernel=self.kernel,
                log_prior=samples[sample].log_prior,
                pixel_weight=weights[sample][None, None],
            )
            return nmi_from_joint_histogram(counts)[0]

        return pair_score


def _check_reliability(reliability: object) -> None:
    if not isinstance(reliability, bool):
        raise TypeError(f"reliability must be True or False, got {reliability!r}")
