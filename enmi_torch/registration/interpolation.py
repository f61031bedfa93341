"""The map between its cells: cubic B-spline or bilinear samples, and their gradients, at continuous positions.

:func:`~enmi_torch.registration.register` fits the captured values by the map's values under the captured pixels at a
continuous pose, so it needs the map between its cells. A map cell is the mean of the scene over the cell (an aerial
photograph averaged into cells, a lidar grid), and so is a captured pixel: the question is what the mean over a
cell-sized window moved by a fraction of a cell is.

* ``"bspline"`` (the default): the cubic B-spline that interpolates the map's cells. It is the area-consistent answer
  for a scene that is a smooth quadratic spline: the quadratic spline whose means over the cells are the map's
  cells, averaged over the moved window, is this cubic B-spline (the mean of a B-spline of degree ``n`` over a unit
  window is one of degree ``n + 1``). The map is prefiltered once (the spline's coefficients, with the map mirrored
  about its first and last cells) and each sample reads the 4 x 4 coefficients around it.
* ``"bilinear"``: the same reasoning for a scene constant over each cell (degree 0): the mean over the moved window
  mixes neighbouring cells in proportion to their overlap, which is bilinear interpolation. A real scene varies
  within a cell, so between cells bilinear samples are blurred (most halfway, the mean of two cells): on 3 x 3 block
  means of aerial photographs moved by a third of a cell, registration through them ends about twice as far from
  the truth as through the B-spline (the docs' localization results page).

Positions are map ``(x, y)`` in cells (column, row), cell centres on integers.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

INTERPOLATIONS = ("bspline", "bilinear")
# Taps per axis, and the first tap's offset from the cell at or before the position.
_TAPS = {"bspline": (4, -1), "bilinear": (2, 0)}


def bspline_coefficients(reference: Tensor) -> Tensor:
    """The cubic B-spline coefficients ``(..., Hm, Wm)`` whose spline interpolates ``reference`` at every cell.

    The map is extended by mirroring about its first and last cells (whole-sample symmetric, as Unser's recursive
    prefilter assumes), so the coefficients solve ``(c[k - 1] + 4 c[k] + c[k + 1]) / 6 = reference[k]`` along each
    axis with ``c[-1] = c[1]``; the system is solved exactly in the Fourier domain of the mirrored map.

    Example:
        >>> reference = torch.tensor([[1.0, 2.0, 0.0, 5.0]], dtype=torch.float64)
        >>> coefficients = bspline_coefficients(reference)
        >>> mirrored = torch.cat([coefficients[:, 1:2], coefficients, coefficients[:, 2:3]], 1)
        >>> ((mirrored[:, :-2] + 4 * mirrored[:, 1:-1] + mirrored[:, 2:]) / 6).round(decimals=9).tolist()
        [[1.0, 2.0, 0.0, 5.0]]
    """
    height, width = reference.shape[-2:]
    extended = _mirrored(_mirrored(reference, -1), -2)
    rows, cols = extended.shape[-2:]
    response = _spline_spectrum(rows, reference, full=True)[:, None] * _spline_spectrum(cols, reference, full=False)
    coefficients = torch.fft.irfft2(torch.fft.rfft2(extended) / response, s=(rows, cols))
    return coefficients[..., :height, :width]


def _mirrored(values: Tensor, dim: int) -> Tensor:
    """``values`` extended to ``2 n - 2`` along ``dim`` by mirroring about its first and last entries."""
    size = values.shape[dim]
    if size <= 2:
        return values
    return torch.cat([values, values.narrow(dim, 1, size - 2).flip(dim)], dim)


def _spline_spectrum(length: int, like: Tensor, full: bool) -> Tensor:
    """The DFT ``(4 + 2 cos w) / 6`` of the sampled cubic B-spline over ``length`` points (rfft's half if not full)."""
    count = length if full else length // 2 + 1
    frequency = torch.arange(count, dtype=like.dtype, device=like.device) * (2 * math.pi / length)
    return (4 + 2 * torch.cos(frequency)) / 6


def _reflect(index: Tensor, size: int) -> Tensor:
    """Indices mirrored about the first and last cells into ``[0, size)`` (at most ``size - 1`` cells outside)."""
    if size == 1:
        return torch.zeros_like(index)
    index = torch.where(index < 0, -index, index)
    return torch.where(index > size - 1, 2 * (size - 1) - index, index).clamp(0, size - 1)


# Each tap's weight as a polynomial in the fraction ``f`` of the position past its cell: ``w_t(f) = sum_p K[t, p] f^p``.
_POLYNOMIALS = {
    "bspline": (
        (1 / 6, -1 / 2, 1 / 2, -1 / 6),  # (1 - f)^3 / 6, the tap one cell before
        (2 / 3, 0.0, -1.0, 1 / 2),  # (3 f^3 - 6 f^2 + 4) / 6, the cell itself
        (1 / 6, 1 / 2, 1 / 2, -1 / 2),  # (-3 f^3 + 3 f^2 + 3 f + 1) / 6, the next cell
        (0.0, 0.0, 0.0, 1 / 6),  # f^3 / 6, two cells on
    ),
    "bilinear": ((1.0, -1.0), (0.0, 1.0)),  # 1 - f, f
}


class MapSampler:
    """A map ready to be sampled at continuous positions, with the gradient of the samples in the position.

    Between cells ``(r, c)`` and ``(r + 1, c + 1)`` the interpolant is one polynomial in the fractions ``(fy, fx)``
    past the cell (bicubic for the B-spline, bilinear), ``py' A px`` with ``px = (1, fx, fx^2, fx^3)``: ``A = K' V K``
    from the 4 x 4 (2 x 2) coefficients ``V`` around the cell and the taps' weight polynomials ``K``. The table of
    every cell's ``A`` is built once; a sample reads its cell's row and evaluates the polynomial and its derivatives.

    Args:
        reference: ``(1 or B, 1, Hm, Wm)`` map, finite (unobserved cells filled beforehand, e.g. by
            :func:`fill_unobserved`).
        interpolation: one of :data:`INTERPOLATIONS`.

    Example:
        >>> reference = torch.arange(20.0, dtype=torch.float64).reshape(1, 1, 4, 5) ** 2
        >>> sampler = MapSampler(reference, "bspline")
        >>> values, _ = sampler.sample(torch.tensor([[[[2.0, 1.0], [2.5, 1.0]]]], dtype=torch.float64))
        >>> values.round(decimals=4).tolist()  # on a cell, the cell; halfway to 64, the spline (bilinear: 56.5)
        [[[49.0, 55.375]]]
    """

    def __init__(self, reference: Tensor, interpolation: str) -> None:
        self.interpolation = interpolation
        self.height, self.width = reference.shape[-2:]
        taps, first = _TAPS[interpolation]
        table = bspline_coefficients(reference) if interpolation == "bspline" else reference
        rows = _reflect(torch.arange(first, self.height + first + taps - 1, device=table.device), self.height)
        cols = _reflect(torch.arange(first, self.width + first + taps - 1, device=table.device), self.width)
        padded = table[:, :, rows][..., cols]  # (1 or B, 1, Hm + taps - 1, Wm + taps - 1)
        polynomials = torch.tensor(_POLYNOMIALS[interpolation], dtype=table.dtype, device=table.device)
        # A[p, q] = sum_ts K[t, p] K[s, q] V[t, s] for every cell at once: a correlation with taps x taps kernels.
        kernels = torch.einsum("tp,sq->pqts", polynomials, polynomials).reshape(taps * taps, 1, taps, taps)
        # One table per power q of fx, each row the coefficients of fy's powers p: [q][cell, p], contiguous per q.
        polynomial = F.conv2d(padded, kernels).reshape(-1, taps, taps, self.height * self.width)  # (maps, p, q, cells)
        self.table = polynomial.permute(2, 0, 3, 1).reshape(taps, -1, taps).contiguous()
        self.maps, self.degree = table.shape[0], taps

    def sample(
        self, positions: Tensor, gradient: bool = False, maps: Tensor | None = None
    ) -> tuple[Tensor, Tensor | None]:
        """Samples ``(B, h, w)`` at positions ``(B, h, w, 2)`` and, if asked, their gradient ``(B, h, w, 2)``.

        Both are in the positions' dtype, 0 off the map; the gradient is in ``(x, y)``. ``maps``: ``(B,)`` which of
        the sampler's maps each row of positions is on (a sampler of one map per image, asked about some of the
        images); ``None``: row ``b`` on map ``b`` (or all on the one map). The samples are differentiable in the
        positions (and in the map where it requires gradients); the gradient asked for is computed in closed form,
        without autograd.
        """
        batch = positions.shape[0]
        x, y = positions.unbind(-1)
        column = x.detach().floor().clamp(0, self.width - 1)
        row = y.detach().floor().clamp(0, self.height - 1)
        cell = row * self.width + column
        if self.maps > 1:
            which = torch.arange(batch, device=cell.device) if maps is None else maps
            cell = cell + (which * (self.height * self.width)).to(cell.dtype).view(-1, 1, 1)
        index = cell.long().flatten()
        table = self.table.to(positions.dtype)
        by_power = [table[power].index_select(0, index).view(*x.shape, self.degree) for power in range(self.degree)]
        fraction_x, fraction_y = (x - column)[..., None], y - row
        along_x = _horner(by_power, fraction_x)  # (B, h, w, taps): the coefficient of each power of fy at fx
        on_map = (x >= 0) & (x <= self.width - 1) & (y >= 0) & (y <= self.height - 1)
        values = torch.where(on_map, _horner(along_x.unbind(-1), fraction_y), 0.0)
        if not gradient:
            return values, None
        slope_x = _horner(_horner(by_power, fraction_x, derivative=True).unbind(-1), fraction_y)
        slope_y = _horner(along_x.unbind(-1), fraction_y, derivative=True)
        return values, torch.where(on_map[..., None], torch.stack([slope_x, slope_y], -1), 0.0)


def _horner(coefficients: list[Tensor] | tuple[Tensor, ...], at: Tensor, derivative: bool = False) -> Tensor:
    """The polynomial ``sum_p coefficients[p] at^p`` (or its derivative in ``at``), by Horner's rule."""
    size = len(coefficients)
    if derivative:
        value = (size - 1) * coefficients[size - 1]
        for power in range(size - 2, 0, -1):
            value = torch.addcmul(power * coefficients[power], value, at)
        return value
    value = coefficients[size - 1]
    for power in range(size - 2, -1, -1):
        value = torch.addcmul(coefficients[power], value, at)  # one fused step: c + value * at
    return value


def fill_unobserved(reference: Tensor, observed: Tensor) -> Tensor:
    """``reference`` with each unobserved cell set to the mean of the observed cells nearest it.

    A B-spline's prefilter spreads every cell over its neighbours (by ``0.268^d`` at ``d`` cells): filled with the
    nearby mean, an unobserved cell leans on the observed ones next to it as little as a plausible value can. The
    neighbourhood grows (3, 5, 9, ... cells) until it holds an observed cell; a map with none gives zeros.
    """
    weight = observed.to(reference.dtype)
    values = torch.where(observed, reference, 0.0)
    filled = values
    missing = ~observed
    radius = 1
    while bool(missing.any()) and radius < 2 * max(reference.shape[-2:]):
        size = 2 * radius + 1
        total = F.avg_pool2d(values, size, 1, radius, count_include_pad=False)
        count = F.avg_pool2d(weight, size, 1, radius, count_include_pad=False)
        found = missing & (count > 0)
        filled = torch.where(found, total / count.clamp_min(torch.finfo(count.dtype).tiny), filled)
        missing = missing & ~found
        radius *= 2
    return filled
