"""FFT correlation of captured planes with reference planes at every placement, the core of the dense surfaces.

With the reference hard-binned, the sums a score needs at the placement with the captured image's top-left pixel on
reference cell ``s`` are cross-correlations, ``sum_n captured_plane[n] * reference_plane[n + s]``: all of them come
from one batched real FFT of each side's planes, a product per plane pair and a pruned inverse FFT (rows first,
cropped to the placements, then columns). Box sums give the exact counts of indicator planes.
"""

from __future__ import annotations

from collections.abc import Iterator

import torch
from torch import Tensor

# The product of one captured plane with a block of reference planes (whole half spectra) stays near this many complex
# elements (4 MiB in complex64, 16 reference planes for a 128 x 128 image in a 228 x 228 reference): batched enough for
# the FFTs, small enough for the CPU cache.
_BLOCK_ELEMENTS = 1 << 19


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


class Correlator:
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


def box_sums(planes: Tensor, height: int, width: int) -> Tensor:
    """Sums of 0/1 planes ``(K, H, W)`` over every ``height x width`` box, ``(K, H - height + 1, W - width + 1)``.

    Exact integers: float32 while every partial sum stays below 2^24, float64 beyond. The column sums run over the
    row-summed planes, which are narrower than the reference.
    """
    dtype = torch.float32 if planes.shape[-2] * planes.shape[-1] < 1 << 24 else torch.float64
    cumulative = torch.nn.functional.pad(planes.to(dtype).cumsum(-1), (1, 0))
    cumulative = (cumulative[..., width:] - cumulative[..., :-width]).transpose(-1, -2)
    cumulative = torch.nn.functional.pad(cumulative.cumsum(-1), (1, 0))
    return (cumulative[..., height:] - cumulative[..., :-height]).transpose(-1, -2)
