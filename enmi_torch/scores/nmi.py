"""Normalized mutual information (Studholme) with hard or Parzen bins: the measurement ENMI and ECR are compared to.

Model (:ref:`model-nmi`): ``(H[A] + H[B]) / H[A, B]``, the entropies of the joint histogram of the captured image's
bins (hard, or spread over the nearest bins by a Parzen window) and the reference's hard bins; 2 for images that
determine each other, about 1 for independent ones.

:func:`nmi` of aligned pairs, :func:`nmi_surface` over every placement (by FFT correlation of the captured bin-weight
planes with the reference's bin planes: :func:`~enmi_torch.placement.information.information_surface`, shared with
ENMI), :func:`nmi_loss` and :class:`NMI`. One default throughout: the captured image's ``kernel="triangular"`` Parzen
window (a gradient, so the loss trains); ``kernel="hard"`` gives scikit-image's
``normalized_mutual_information`` (no gradient).
"""

from __future__ import annotations

import torch
from torch import Tensor

from enmi_torch.binning import PARZEN_KERNELS, parzen_weights_unchecked
from enmi_torch.histogram import hard_entropies, joint_histogram_of_inputs, prepare_inputs
from enmi_torch.information import nmi_from_entropies, nmi_from_joint_histogram
from enmi_torch.placement.information import information_surface
from enmi_torch.placement.inputs import Surface, check_inputs
from enmi_torch.scores.base import Score, reduce_loss
from enmi_torch.utils.budget import check_surface_memory
from enmi_torch.utils.checks import check_bins, check_option, check_same_device, check_value_range


def nmi(
    captured: Tensor,
    reference: Tensor,
    *,
    bins: int = 32,
    value_range: tuple[float, float] = (0.0, 256.0),
    kernel: str = "triangular",
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
        kernel: ``"triangular"`` (the default) or ``"xu"`` (Parzen windows, differentiable in ``captured``), or
            ``"hard"`` (unit counts: scikit-image's ``normalized_mutual_information``; no gradient).
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
        >>> nmi(image, image, bins=4, kernel="hard")
        tensor([2.])
        >>> nmi(image, image.transpose(-1, -2), bins=4, kernel="hard")
        tensor([1.])
        >>> nmi(image, image, bins=4)  # the triangular window spreads each value over two bins
        tensor([1.4273])
    """
    check_option("kernel", kernel, ("hard", "triangular", "xu"))
    check_same_device("reference", reference, "captured", captured)
    if kernel == "hard" and reference_kernel == "hard" and _few_pixels(captured, bins):
        # Same score as the hard joint histogram's, with O(pixels) logarithms per sample instead of O(bins^2).
        return nmi_from_entropies(
            *hard_entropies(captured, reference, bins=bins, value_range=value_range, valid_mask=valid_mask)
        )
    inputs = prepare_inputs(captured, reference, bins, value_range, None, valid_mask, kernel, reference_kernel, None)
    return nmi_from_joint_histogram(joint_histogram_of_inputs(inputs, scored=True))


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
    kernel: str = "triangular",
    captured_mask: Tensor | None = None,
    reference_mask: Tensor | None = None,
) -> Surface:
    """NMI of ``captured`` at every placement inside ``reference``, by FFT correlation of bin planes.

    Args:
        captured: captured image ``(B, 1, h, w)``, floating point.
        reference: map section ``(1 or B, 1, Hw, Ww)``, ``Hw >= h``, ``Ww >= w``.
        bins: number of equal-width bins over ``value_range``.
        value_range: ``(low, high)``.
        kernel: the captured image's window, as in :func:`nmi` (the reference is hard-binned).
        captured_mask: bool ``(h, w)``, ``(1, 1, h, w)`` or ``(B, 1, h, w)``; ``False`` pixels are left out.
        reference_mask: bool ``(Hw, Ww)``, ``(1, 1, Hw, Ww)`` or one per reference.

    Returns:
        :class:`Surface`; ``score[b, u, v]`` equals ``nmi(captured[b], reference[b, :, u:u + h, v:v + w], ...)``
        with the same ``kernel``, without gradient.

    Example:
        >>> reference = torch.arange(64.0).reshape(1, 1, 8, 8) * 4
        >>> round(nmi_surface(reference[..., 2:6, 1:5], reference, bins=64, kernel="hard").score[0, 2, 1].item(), 4)
        2.0
    """
    check_option("kernel", kernel, PARZEN_KERNELS)
    bins = check_bins(bins)
    value_range = check_value_range(value_range)
    inputs = check_inputs(captured, reference, captured_mask, reference_mask, value_range, bins=bins)
    check_surface_memory(inputs.captured, inputs.reference, bins)
    with torch.no_grad():
        planes = parzen_weights_unchecked(inputs.captured, bins, value_range, kernel)
        return information_surface(planes, inputs, bins, value_range)


def nmi_loss(
    captured: Tensor,
    reference: Tensor,
    *,
    valid_mask: Tensor | None = None,
    reduction: str = "mean",
    **options,
) -> Tensor:
    """``2 - nmi(captured, reference, **options)`` reduced over the batch: ``NMI(**options).loss(...)``.

    ``reduction``: ``"none"`` (``(B,)``), ``"mean"`` or ``"sum"``; ``options``: those of :class:`NMI` (the default
    ``kernel="triangular"`` carries a gradient; ``kernel="hard"`` has none and is refused).

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> nmi_loss(image, image, bins=4), nmi_loss(image, image.mT, bins=4)
        (tensor(0.5727), tensor(0.9927))
    """
    return NMI(**options).loss(captured, reference, valid_mask=valid_mask, reduction=reduction)


class NMI(Score):
    """NMI as an object: :func:`nmi`, :func:`nmi_surface` and :func:`nmi_loss` with its options.

    Args:
        bins: number of equal-width bins over ``value_range``.
        value_range: ``(low, high)`` of the bins.
        kernel: ``"triangular"`` (the default) or ``"xu"`` (Parzen windows: a gradient for the loss), or ``"hard"``
            (scikit-image's NMI; no gradient, so no loss).
        reference_kernel: the same choice for the reference (``"hard"`` for the surface).

    Example:
        >>> image = torch.arange(16.0).reshape(1, 1, 4, 4) * 16 + 8
        >>> score = NMI(bins=4)
        >>> score(image, image), score.loss(image, image.mT), score.is_differentiable
        (tensor([1.4273]), tensor(0.9927), True)
        >>> NMI(bins=4, kernel="hard")(image, image), NMI(kernel="hard").is_differentiable
        (tensor([2.]), False)
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
        kernel: str = "triangular",
        reference_kernel: str = "hard",
    ) -> None:
        bins = check_bins(bins)
        value_range = check_value_range(value_range)
        check_option("kernel", kernel, PARZEN_KERNELS)
        check_option("reference_kernel", reference_kernel, PARZEN_KERNELS)
        super().__init__(bins=bins, value_range=value_range, kernel=kernel, reference_kernel=reference_kernel)

    @property
    def is_differentiable(self) -> bool:
        """Whether the score carries a gradient to the captured image: not with ``kernel="hard"``."""
        return self.kernel != "hard"

    def check_differentiable(self) -> None:
        """Raise ``ValueError`` for ``kernel="hard"``, naming the kernels that carry a gradient."""
        if not self.is_differentiable:
            raise ValueError(f"{self!r} has no gradient: give kernel='triangular' (the default) or 'xu' for a loss")

    def _value(self, captured, reference, variance, valid_mask) -> Tensor:
        return nmi(captured, reference, valid_mask=valid_mask, **self._options)

    def _surface(self, captured, reference, variance, captured_mask, reference_mask) -> Surface:
        if self.reference_kernel != "hard":
            raise ValueError(f"NMI's surface needs reference_kernel='hard', got {self.reference_kernel!r}")
        masks = {"captured_mask": captured_mask, "reference_mask": reference_mask}
        options = {name: value for name, value in self._options.items() if name != "reference_kernel"}
        return nmi_surface(captured, reference, **options, **masks)

    def _loss(self, captured, reference, variance, valid_mask, reduction) -> Tensor:
        return reduce_loss(2 - self._value(captured, reference, variance, valid_mask), reduction)
