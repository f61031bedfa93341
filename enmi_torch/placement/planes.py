"""The reference's planes and the moment planes shared by the surfaces, on top of :mod:`~enmi_torch.placement.fft`.

:class:`ReferencePlanes`: the indicator planes of a hard-binned reference's bins (and its mask), computed once per
reference, with their exact box-summed counts. :func:`moment_blocks`: the correlations of three captured planes with
the reference's valid mask, centred values and their squares (NCC, ECR's linear response).
"""

from __future__ import annotations

from collections.abc import Iterator

import torch
from torch import Tensor

from enmi_torch.binning import hard_bin_index
from enmi_torch.placement.fft import Correlator, box_sums
from enmi_torch.placement.inputs import SurfaceInputs


class ReferencePlanes:
    """The reference's side of the information surfaces, computed once per reference.

    ``spectra`` holds the indicator planes of the bins present in the reference, then the reference mask where it leaves
    cells out (``complete`` is ``False``); ``present_bins`` the bin of each indicator plane. :meth:`counts` gives, on
    demand, the exact number of cells of each present bin and of valid cells under a captured image at each placement.
    """

    def __init__(
        self, correlator: Correlator, window_bins: Tensor, reference_valid: Tensor, bins: int, dtype: torch.dtype
    ) -> None:
        present = torch.bincount(window_bins.flatten(), minlength=bins + 1)[:bins].nonzero()[:, 0]
        self.complete = bool(reference_valid.all())
        # One scatter of ones into zeroed planes: far cheaper than comparing every cell with every bin.
        plane_of_bin = torch.full((bins + 1,), present.shape[0], dtype=torch.int64, device=window_bins.device)
        plane_of_bin[present] = torch.arange(present.shape[0], device=window_bins.device)
        cells = plane_of_bin[window_bins].view(1, -1)
        planes = torch.zeros(present.shape[0] + 1, cells.shape[1], dtype=dtype, device=window_bins.device)
        planes = planes.scatter_(0, cells, 1.0)[:-1].view(-1, *window_bins.shape)  # the last row took masked cells
        if not self.complete:
            planes = torch.cat([planes, reference_valid[None].to(dtype)])
        self.spectra = correlator.spectra(planes, captured=False)
        self.bin_count = present.shape[0]
        self.present_bins = present  # the bin index of each indicator plane
        self._labels = torch.cat([present, present.new_tensor([bins])])
        self._window_bins = window_bins
        self._counts: Tensor | None = None

    def counts(self, height: int, width: int, dtype: torch.dtype) -> Tensor:
        """``(Kr + 1, rows, cols)``: cells of each present bin, then valid cells, under a ``height x width`` image."""
        if self._counts is None:
            indicators = self._window_bins == self._labels[:, None, None]  # the last plane: masked cells
            counts = box_sums(indicators, height, width).to(dtype)
            counts[-1] = counts[-1].neg_().add_(height * width)
            self._counts = counts
        return self._counts


def per_sample_reference_planes(
    correlator: Correlator, inputs: SurfaceInputs, bins: int, value_range: tuple[float, float]
) -> Iterator[tuple[int, ReferencePlanes]]:
    """Each sample's index and its reference's :class:`ReferencePlanes` (built once when one reference is shared)."""
    windows = inputs.reference.shape[0]
    window_bins = torch.where(inputs.reference_valid, hard_bin_index(inputs.reference, bins, value_range), bins)
    reference = None
    for sample in range(inputs.captured.shape[0]):
        window_index = sample if windows > 1 else 0
        if reference is None or windows > 1:
            reference = ReferencePlanes(
                correlator, window_bins[window_index], inputs.reference_valid[window_index], bins, inputs.captured.dtype
            )
        yield sample, reference


def moment_blocks(inputs: SurfaceInputs, local_planes: Tensor) -> Iterator[Tensor]:
    """Per sample, the ``(3, 3, rows, cols)`` correlations of three captured planes with three reference planes.

    The captured planes ``(B, 3, h, w)`` meet the reference's valid mask, centred values and their squares at every
    placement: the sums behind NCC and ECR's linear response.
    """
    correlator = Correlator(tuple(inputs.captured.shape[1:]), tuple(inputs.reference.shape[1:]))
    windows = inputs.reference.shape[0]
    reference_valid = inputs.reference_valid.to(inputs.captured.dtype)
    # Centring on the reference's valid mean keeps the sums small, so the FFT round-off stays relative.
    centred = (inputs.reference - masked_mean(inputs.reference, reference_valid)) * reference_valid
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


def masked_mean(images: Tensor, valid: Tensor) -> Tensor:
    """``(B, 1, 1)``: the mean of ``images`` ``(B, h, w)`` over its ``valid`` pixels (0 where none is)."""
    return ((images * valid).sum((-2, -1)) / valid.sum((-2, -1)).clamp_min(1)).reshape(-1, 1, 1)
