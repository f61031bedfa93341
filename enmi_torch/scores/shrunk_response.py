"""ECR's default response: one mean per reference bin, shrunk toward an increasing line by as much as the data allow.

Model (:ref:`model-shrunk`): ``mu_j = a + b u_j + d_j``, ``d_j ~ N(0, delta^2)``, ``b >= 0``, ``u_j`` the bin's index;
with the deviations integrated out, the log-likelihood ratio against one mean is a closed form in the per-bin sums
``W_j``, ``S_j`` (:func:`shrunk_llr_terms`), and ``delta^2`` is taken where it is largest (:func:`shrunk_llr`).

The binned response fits one free mean per reference bin (any function of the map, monotonic or not); the linear
response fits ``a + b r``. With few pixels per bin and much noise the free means fit the noise, and a near-linear pair
scores far below what the line finds; where the map and the image are not monotonically related the line finds
nothing. ``delta^2 = 0`` is the linear response on the bin centres; a large ``delta^2`` is the binned response less
an Occam factor per bin. ECR is ``(LLR - 1 / 2) / n``, as the linear response's.

``delta^2`` is a property of the sensor and the scene, not of a placement, so it is estimated once where the images
are aligned and held at every placement (as ECR's model variance ``tau^2``): an aligned pair takes the maximum of
its own profile (:func:`shrunk_llr`), a surface the ``delta^2`` of the best placement of a cheap first pass. Taken
per placement instead, the profile lets a wrong placement buy back the free bin means: there the bin means of a
photograph scatter by its own structure (spatially correlated pixels, far more than independent pixels would), and
the profile leaves the line to fit it. Held fixed, the shrunk response scores as the line where the sensor is
near-linear and as the bins where it is not.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

# The grid of delta^2 a profile is first evaluated on, as fractions of the squared value range: 0, then 1e-8 to 10 a
# decade apart (beyond 10, the binned response's limit). Around the best grid point the search halves its step twice
# (two evaluations each) and a parabola in log delta^2 through the last triple gives the maximum: the LLR is smooth in
# log delta^2.
_GRID_EXPONENTS = range(-8, 2)
_HALVINGS = 2


def response_variance_grid(value_range: tuple[float, float]) -> tuple[float, ...]:
    """The ``delta^2`` values a placement's LLR is first evaluated at: 0, then ``R^2 10^k``, ``k = -8 .. 1``.

    ``R`` is the width of ``value_range``.

    Example:
        >>> grid = response_variance_grid((0.0, 256.0))
        >>> len(grid), grid[0], round(grid[-1])
        (11, 0.0, 655360)
    """
    span = (value_range[1] - value_range[0]) ** 2
    return (0.0, *(span * 10.0**k for k in _GRID_EXPONENTS))


def bin_positions(bins: int, dtype: torch.dtype, device: torch.device | None = None) -> Tensor:
    """``u_j``: each bin's centre on a scale of bin widths, centred on the range's middle, ``(bins,)``.

    Example:
        >>> bin_positions(4, torch.float64)
        tensor([-1.5000, -0.5000,  0.5000,  1.5000], dtype=torch.float64)
    """
    return torch.arange(bins, dtype=dtype, device=device) - (bins - 1) / 2


class _ShrunkTerms:
    """The LLR of :func:`shrunk_llr_terms` for one set of per-bin sums ``(K, M)``, at any ``delta^2``.

    ``positions``: ``(K,)``, shared by the ``M`` sets (a matrix product sums over the bins), or ``(K, M)``.
    """

    def __init__(self, weight: Tensor, weighted_value: Tensor, positions: Tensor) -> None:
        occupied = weight > 0
        self.weight = torch.where(occupied, weight, 0.0)
        self.value = torch.where(occupied, weighted_value, 0.0)
        self.powers = torch.stack([torch.ones_like(positions), positions, positions.square()])  # (3, K[, M])
        self.tiny = torch.finfo(weight.dtype).tiny
        self.eps = 64 * torch.finfo(weight.dtype).eps
        self.level = self.value.sum(0).square() / self.weight.sum(0).clamp_min(self.tiny)

    def __call__(self, response_variance: float | Tensor) -> Tensor:
        scaled = self.weight * response_variance
        shrink = (scaled + 1).reciprocal()
        occam = scaled.log1p().sum(0)
        total, first, second = self._moments(shrink * self.weight, 3)  # sums of s W, s W u, s W u^2 over the bins
        trend_value = shrink * self.value
        value, covariance = self._moments(trend_value, 2)
        deviations = response_variance * torch.linalg.vecdot(trend_value, self.value, dim=0)
        total = total.clamp_min(self.tiny)
        covariance = covariance - first * value / total
        spread = second - first.square() / total
        sloped = (spread > self.eps * second) & (covariance > 0)
        slope_term = torch.where(sloped, covariance.square() / torch.where(sloped, spread, 1.0), 0.0)
        return 0.5 * (deviations + value.square() / total - self.level + slope_term - occam)

    def _moments(self, values: Tensor, count: int) -> Tensor:
        """``sum_j values_j u_j^p`` for ``p < count``, ``(count, M)``."""
        if self.powers.dim() == 2:
            return self.powers[:count] @ values
        return (self.powers[:count] * values).sum(1)


def _flat(weight: Tensor, weighted_value: Tensor, positions: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The sums as ``(K, M)`` and the positions as ``(K,)`` (shared by every set) or ``(K, M)``."""
    bins = weight.shape[0]
    if positions.numel() == bins:
        positions = positions.reshape(bins)
    else:
        positions = positions.expand(weight.shape).reshape(bins, -1)
    return weight.reshape(bins, -1), weighted_value.reshape(bins, -1), positions


def shrunk_llr_terms(
    weight: Tensor, weighted_value: Tensor, positions: Tensor, response_variance: float | Tensor
) -> Tensor:
    """``LLR(delta^2)`` of the shrunk response for per-bin sums with the bins first, ``(K, ...)`` -> ``(...)``.

    ``weight`` is ``W_j`` (0 for an empty bin), ``weighted_value`` ``S_j`` (values centred on any constant),
    ``positions`` ``u_j`` ``(K,)``, ``(K, 1, ...)`` or one per set of sums ``(K, ...)``, ``response_variance``
    ``delta^2`` (a number, or one per set of sums, broadcastable to ``(...)``). Differentiable in the sums.
    """
    if isinstance(response_variance, Tensor):
        response_variance = response_variance.to(weight.dtype).expand(weight.shape[1:]).reshape(-1)
    return _ShrunkTerms(*_flat(weight, weighted_value, positions))(response_variance).view(weight.shape[1:])


def shrunk_llr(
    weight: Tensor, weighted_value: Tensor, positions: Tensor, value_range: tuple[float, float]
) -> tuple[Tensor, Tensor]:
    """The LLR maximised over ``delta^2`` and the ``delta^2`` that maximises it, ``(...)`` each.

    Arguments as :func:`shrunk_llr_terms`'s. The LLR is evaluated on :func:`response_variance_grid`; where the best
    point has a neighbour on each side (not ``delta^2 = 0`` nor the grid's end) the search evaluates it half a step
    to either side, moves to the best of the three, and halves again; a parabola in ``log delta^2`` through the last
    triple gives the maximum (within a few hundredths of a nat of it) and where it lies. ``delta^2 = 0`` or the
    grid's end, where best, are taken as they are. Differentiable in the sums (through the last triple).

    Example:
        >>> weight = torch.full((4,), 10.0, dtype=torch.float64)
        >>> line = 10.0 * torch.tensor([-3.0, -1.0, 1.0, 3.0], dtype=torch.float64)  # S_j = W_j m_j, m on a line
        >>> vee = 10.0 * torch.tensor([3.0, -3.0, -3.0, 3.0], dtype=torch.float64)  # a V-shaped response
        >>> positions = bin_positions(4, torch.float64)
        >>> shrunk_llr(weight, line, positions, (0.0, 4.0))[1], shrunk_llr(weight, vee, positions, (0.0, 4.0))[1] > 1
        (tensor(0., dtype=torch.float64), tensor(True))
    """
    grid = response_variance_grid(value_range)
    terms = _ShrunkTerms(*_flat(weight, weighted_value, positions))
    values = torch.stack([terms(response_variance) for response_variance in grid])  # (G, M)
    best = values.detach().argmax(0)
    inner = (best > 0) & (best < len(grid) - 1)
    index = best.clamp(1, len(grid) - 2)
    low, middle, high = (values.gather(0, (index + side)[None])[0] for side in (-1, 0, 1))
    dtype = terms.weight.dtype
    centre = torch.tensor(grid[1:], dtype=dtype, device=terms.weight.device).log()[index - 1]
    step = math.log(10)
    for _ in range(_HALVINGS):
        step = step / 2
        below, above = (terms(torch.where(inner, (centre + side * step).exp(), 0.0)) for side in (-1, 1))
        go_low = (below.detach() > middle.detach()) & (below.detach() >= above.detach())
        go_high = ~go_low & (above.detach() > middle.detach())
        centre = centre + step * (go_high.to(dtype) - go_low.to(dtype))
        low, middle, high = (
            torch.where(go_low, low, torch.where(go_high, middle, below)),
            torch.where(go_low, below, torch.where(go_high, above, middle)),
            torch.where(go_low, middle, torch.where(go_high, high, above)),
        )
    curvature = 2 * middle - low - high  # >= 0: the middle is the best of the three
    bent = curvature > 0
    safe = torch.where(bent, curvature, 1.0)
    vertex = torch.where(bent, (high - low) / (2 * safe), 0.0)  # within half a step of the middle
    refined = torch.where(bent, middle + (high - low).square() / (8 * safe), middle)
    llr = torch.where(inner, refined, values.gather(0, best[None])[0])
    at_grid = torch.tensor(grid, dtype=dtype, device=terms.weight.device)[best]
    chosen = torch.where(inner, (centre + vertex.detach() * step).exp(), at_grid)
    shape = weight.shape[1:]
    return llr.view(shape), chosen.view(shape)
