"""Normalized mutual information (Studholme) with hard or Parzen bins: the measurement ENMI and ECR are compared to.

:func:`nmi` of aligned pairs (hard bins by default, as scikit-image's
``normalized_mutual_information``), :func:`nmi_surface` over every placement (hard bins, by FFT correlation of the bin
planes: :func:`~enmi_torch.placement.information.information_surface`, shared with ENMI), :func:`nmi_loss` and
:class:`NMI`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from enmi_torch.binning import PARZEN_KERNELS, hard_bin_index
from enmi_torch.histogram import _joint_histogram, _prepare, hard_entropies
from enmi_torch.information import _nmi_from_entropies, nmi_from_joint_histogram
from enmi_torch.placement.information import information_surface
from enmi_torch.placement.inputs import Surface, check_inputs
from enmi_torch.scores.base import REDUCTIONS, Score, reduce_loss
from enmi_torch.utils.budget import check_surface_memory
from enmi_torch.utils.checks import check_bins, check_option, check_same_device, check_value_range


def nmi(
    captured: Tensor,
    reference: Tensor,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    kernel: str = "hard",
    reference_kernel: str = "hard",
    valid_mask: Tensor | None = None,
) -> Tensor:
    """Normalized mutual information of each captured/reference pair, ``(B,)``.

    Args:
        captured: ``(B, 1, H, W)`` or ``(B, H, W)`` (flat samples: ``(B, 1, N)``), floating point.
        reference: same shape as ``captured``, or ``(C, *captured.shape)`` to score each captured image against
            ``C`` candidates (the captured bins are computed once).
        bins: number of equal-width bins over ``value_range``.
        value_range: ``(low, high)``; values outside are clipped into the edge bins.
        kernel: ``"hard"`` (unit counts, as scikit-image; no gradient), ``"triangular"`` or ``"xu"`` (Parzen
            windows, differentiable in ``captured``).
        reference_kernel: the same choice for ``reference``.
        valid_mask: bool ``(H, W)``, ``(1, 1, H, W)`` or ``(B, 1, H, W)``; ``False`` pixels are left out.

    Returns:
        ``(H[A] + H[B]) / H[A, B]`` in ``[1, 2]``: 2 for images that determine each other, about 1 for independent
        ones; ``(B,)``, or ``(C, B)`` for candidates. Same dtype as ``captured``.

    Raises:
        MemoryBudgetError: for soft kernels whose ``(C, B, bins, bins)`` histograms and entropies would exceed the
            memory budget (see :func:`~enmi_torch.histogram.joint_histogram`); hard bins need no ``bins^2`` table.

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> nmi(image, image, bins=4)
        tensor([2.])
        >>> nmi(image, image.transpose(-1, -2), bins=4)
        tensor([1.])
    """
    check_option("kernel", kernel, ("hard", "triangular", "xu"))
    check_same_device("reference", reference, "captured", captured)
    if kernel == "hard" and reference_kernel == "hard" and _few_pixels(captured, bins):
        # Same score as the hard joint histogram's, with O(pixels) logarithms per sample instead of O(bins^2).
        return _nmi_from_entropies(
            *hard_entropies(captured, reference, bins=bins, value_range=value_range, valid_mask=valid_mask)
        )
    inputs = _prepare(captured, reference, bins, value_range, None, valid_mask, kernel, reference_kernel, None)
    return nmi_from_joint_histogram(_joint_histogram(inputs, scored=True))


def _few_pixels(captured: Tensor, bins: int) -> bool:
    """Whether an image has fewer than ``bins^2 / 4`` pixels, where pixel-wise hard entropies cost less.

    Below that the ``bins x bins`` joint histogram's cells outnumber the pixels.
    """
    if not isinstance(captured, Tensor) or captured.ndim < 2 or isinstance(bins, bool) or not isinstance(bins, int):
        return False
    if captured.shape[0] == 0:
        return False  # the joint histogram's checks refuse an empty batch
    return 4 * captured[0].numel() < bins * bins


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
    inputs = check_inputs(captured, reference, captured_mask, reference_mask, value_range, bins=bins)
    check_surface_memory(inputs.captured, inputs.reference, bins)
    with torch.no_grad():
        one_hot = torch.nn.functional.one_hot(hard_bin_index(inputs.captured, bins, value_range), bins)
        return information_surface(one_hot.to(inputs.captured.dtype), inputs, bins, value_range)


def nmi_loss(captured: Tensor, reference: Tensor, *, reduction: str = "mean", **options) -> Tensor:
    """``2 - nmi(captured, reference, **options)`` reduced over the batch.

    ``reduction``: ``"none"`` (``(B,)``), ``"mean"`` or ``"sum"``; ``options``: the keyword arguments of
    :func:`nmi` (``kernel`` defaults to ``"triangular"``: a gradient; ``"hard"`` is the measurement).

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> nmi_loss(image, image, bins=4, kernel="hard"), nmi_loss(image, image.mT, bins=4, kernel="hard")
        (tensor(0.), tensor(1.))
    """
    check_option("reduction", reduction, REDUCTIONS)
    return reduce_loss(2 - nmi(captured, reference, **{"kernel": "triangular", **options}), reduction)


class NMI(Score):
    """NMI as an object: :func:`nmi`, :func:`nmi_surface` and :func:`nmi_loss` with its options.

    Args:
        bins: number of equal-width bins over ``value_range``.
        value_range: ``(low, high)`` of the bins.
        kernel: ``"hard"`` (the measurement, the only one the surface takes), ``"triangular"`` or ``"xu"`` (Parzen
            windows: a gradient for the loss).
        reference_kernel: the same choice for the reference (``"hard"`` for the surface).

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> score = NMI(bins=4)
        >>> score(image, image), score.loss(image, image.mT)
        (tensor([2.]), tensor(1.))
    """

    name = "nmi"
    uses_variance = False
    empty_score = 1.0
    _bins_captured = True

    def __init__(
        self,
        *,
        bins: int = 32,
        value_range: tuple[float, float] = (0.0, 256.0),
        kernel: str = "hard",
        reference_kernel: str = "hard",
    ) -> None:
        bins = check_bins(bins)
        value_range = check_value_range(value_range)
        check_option("kernel", kernel, PARZEN_KERNELS)
        check_option("reference_kernel", reference_kernel, PARZEN_KERNELS)
        super().__init__(bins=bins, value_range=value_range, kernel=kernel, reference_kernel=reference_kernel)

    def _value(self, captured, reference, variance, valid_mask) -> Tensor:
        return nmi(captured, reference, valid_mask=valid_mask, **self._options)

    def _surface(self, captured, reference, variance, captured_mask, reference_mask) -> Surface:
        if (self.kernel, self.reference_kernel) != ("hard", "hard"):
            raise ValueError(
                f"NMI's surface needs kernel='hard' and reference_kernel='hard', got {self.kernel!r} and "
                f"{self.reference_kernel!r}"
            )
        masks = {"captured_mask": captured_mask, "reference_mask": reference_mask}
        return nmi_surface(captured, reference, bins=self.bins, value_range=self.value_range, **masks)

    def _loss(self, captured, reference, variance, valid_mask, reduction) -> Tensor:
        return nmi_loss(captured, reference, valid_mask=valid_mask, reduction=reduction, **self._options)
