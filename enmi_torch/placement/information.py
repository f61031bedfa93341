"""NMI of the joint histograms at every placement, by FFT: the information surface that ENMI and NMI share.

With the reference hard-binned, the joint histogram of the captured image placed with its top-left pixel at
reference cell ``s`` is

    ``J[i, j](s) = sum_n W[n, i] captured_valid[n] * R_j[n + s]``,   ``R_j = reference_valid * [reference bin == j]``,

the cross-correlation of the captured image's bin-weight plane ``W[:, i]`` (a Gaussian likelihood for ENMI, one-hot
for NMI) with the reference's bin-indicator plane ``R_j``: ``K x K`` correlations per placement from
:class:`~enmi_torch.placement.fft.Correlator`; bins whose planes are empty on either side are skipped, and the masks
add a plane only where they leave pixels out (otherwise the marginals are constants and box sums).
"""

from __future__ import annotations

import torch
from torch import Tensor

from enmi_torch.information import nmi_from_entropies
from enmi_torch.placement.fft import Correlator
from enmi_torch.placement.inputs import Surface, SurfaceInputs
from enmi_torch.placement.planes import per_sample_reference_planes


class EntropySum:
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


def information_surface(
    plane_weights: Tensor,
    inputs: SurfaceInputs,
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
    _, height, width = inputs.captured.shape
    correlator = Correlator((height, width), tuple(inputs.reference.shape[1:]))
    dtype = inputs.captured.dtype
    weighted = pixel_weight is not None
    pixel_planes = pixel_weight if weighted else inputs.captured_valid.to(dtype)
    plane_weights = (plane_weights * pixel_planes.unsqueeze(-1)).permute(0, 3, 1, 2)
    shape = (correlator.rows, correlator.cols)
    scores, overlaps = [], []
    for sample, reference in per_sample_reference_planes(correlator, inputs, bins, value_range):
        captured_valid = inputs.captured_valid[sample]
        local_complete = bool(captured_valid.all()) and not weighted
        weights = plane_weights[sample]
        weights = weights[weights.flatten(1).amax(1).nonzero()[:, 0]]
        extra = [] if local_complete else [pixel_planes[sample]] + ([captured_valid.to(dtype)] if weighted else [])
        planes = torch.cat([weights, *(plane[None] for plane in extra)])
        captured = correlator.spectra(planes, captured=True)

        scratch = inputs.captured.new_empty(reference.spectra.shape[0], *shape)
        joint, captured_sum, reference_sum = EntropySum(scratch), EntropySum(scratch), EntropySum(scratch)
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
        score = nmi_from_entropies(captured_entropy, reference_entropy, joint_entropy, informative)
        scores.append(score)
        overlaps.append(overlap)
    return Surface(torch.stack(scores), torch.stack(overlaps))
