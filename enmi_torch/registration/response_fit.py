"""The weighted least-squares fit of captured values by a response of the map's values, refitted at every pose.

A least-squares score (:meth:`~enmi_torch.scores.Score.response_basis`: ECR, NCC) fits the captured values by a
piecewise-linear response with a knot per bin centre, or by an affine one, each pixel with its weight and the knots
optionally pulled toward a line (:meth:`~enmi_torch.scores.Score.least_squares_fit`);
:mod:`~enmi_torch.registration.refine` moves the pose through it.
"""

from __future__ import annotations

import copy

import torch
from torch import Tensor

from enmi_torch.scores import Score
from enmi_torch.scores.base import LeastSquaresFit, ResponseBasis
from enmi_torch.scores.shrunk_response import bin_positions


class ResponseFit:
    """The score's weighted least-squares model of the captured values by the map's, each pixel with its weight.

    Every pixel's predictor is two basis functions: ``(i, 1 - f), (i + 1, f)`` (the hat functions of the knots around
    its map value: the piecewise-linear response) or ``(0, 1), (1, m)`` (the affine response). The normal equations
    are assembled with index sums, ``O(N)`` per image whatever the number of knots.

    Args:
        basis: the score's :meth:`~enmi_torch.scores.Score.response_basis`.
        terms: the score's :meth:`~enmi_torch.scores.Score.least_squares_fit` at the alignment whose pixels count.
    """

    @classmethod
    def of(cls, score: Score, captured: Tensor, warped: Tensor, variance: Tensor | None, valid: Tensor) -> ResponseFit:
        """The fit of ``score`` with its weights read at one alignment (``warped``: the map under ``captured``)."""
        return cls(score.response_basis(), score.least_squares_fit(captured, warped, variance, valid))

    def __init__(self, basis: ResponseBasis, terms: LeastSquaresFit) -> None:
        weights, penalty = terms
        self.weights = weights  # (B, N), zero on pixels that do not count
        self.spline = basis.knots > 0
        self.penalty = None  # (B, size, size): the shrunk response's pull of the knots toward a line
        if self.spline:
            low, high = basis.value_range
            self.step = (high - low) / basis.knots
            self.first = low + 0.5 * self.step  # the first knot: the first bin's centre
            self.size = basis.knots
            if penalty is not None:
                lines = torch.stack([torch.ones(self.size), bin_positions(self.size, torch.float64)], 1)
                projection = lines @ torch.linalg.pinv(lines)
                away = (torch.eye(self.size, dtype=torch.float64) - projection).to(weights.device)
                self.penalty = penalty.to(away)[:, None, None] * away  # float64, as the normal equations
        else:
            self.size = 2

    def rows(self, index: Tensor) -> ResponseFit:
        """The fit of the images ``index`` ``(K,)`` alone (their weights and pulls)."""
        part = copy.copy(self)
        part.weights = self.weights[index]
        part.penalty = None if self.penalty is None else self.penalty[index]
        return part

    def _pairs(self, values: Tensor):
        """Per pixel: the two basis indices, their values, and their derivatives in the map's value."""
        if not self.spline:
            zero, one = torch.zeros_like(values, dtype=torch.long), torch.ones_like(values, dtype=torch.long)
            return (zero, one), (torch.ones_like(values), values), (torch.zeros_like(values), torch.ones_like(values))
        unclamped = (values - self.first) / self.step
        position = unclamped.clamp(0, self.size - 1)
        index = position.detach().floor().clamp(max=self.size - 2).long()
        fraction = position - index
        rate = ((unclamped > 0) & (unclamped < self.size - 1)).to(values.dtype) / self.step
        return (index, index + 1), (1 - fraction, fraction), (-rate, rate)

    def solve(self, captured: Tensor, values: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Residuals ``(B, N)`` (weighted by the square root of the weights), response slopes ``(B, N)``, scores.

        Per pixel in the values' dtype; the normal equations, their solution and the scores (``(B,)`` float64) in
        float64: in float32 a knot with few pixels leaves the equations too ill-conditioned to tell poses apart.
        """
        size = self.size
        indices, parts, slopes = self._pairs(values)
        normal, right = self._normal_equations(captured, indices[0], parts)
        if self.penalty is not None:
            normal = normal + self.penalty
        ridge = 1e-9 * normal.diagonal(dim1=1, dim2=2).amax(1).clamp_min(1e-300)
        normal = normal + ridge[:, None, None] * torch.eye(size, dtype=normal.dtype, device=normal.device)
        coefficients = torch.linalg.solve(normal, right)
        at = [coefficients.gather(1, index).to(values.dtype) for index in indices]
        fitted = parts[0] * at[0] + parts[1] * at[1]
        slope = slopes[0] * at[0] + slopes[1] * at[1]
        residual = self.weights.sqrt() * (captured - fitted)
        wide = torch.float64
        total = self.weights.sum(1, dtype=wide).clamp_min(1e-300)
        mean = (self.weights * captured).sum(1, dtype=wide) / total
        null = (self.weights * (captured - mean[:, None].to(captured.dtype)).square()).sum(1, dtype=wide)
        count = (self.weights > 0).sum(1).clamp_min(1).to(wide)
        misfit = residual.square().sum(1, dtype=wide)
        if self.penalty is not None:
            misfit = misfit + (coefficients[:, None, :] @ self.penalty @ coefficients[:, :, None]).flatten()
        score = 0.5 * (null - misfit) / count
        return residual, slope, score

    def _normal_equations(self, captured: Tensor, index: Tensor, parts) -> tuple[Tensor, Tensor]:
        """``X' W X`` ``(B, size, size)`` and ``X' W y`` ``(B, size)`` of the two-term predictors, float64.

        The piecewise-linear basis gives a tridiagonal ``X' W X``: each pixel adds to its knot pair ``(i, i + 1)``
        only, so five sums per knot (one scatter) hold all of it.
        """
        batch, size = captured.shape[0], self.size
        low, high = parts
        weighted_low, weighted_high = self.weights * low, self.weights * high
        terms = [weighted_low * low, weighted_high * high, weighted_low * high, weighted_low * captured]
        terms.append(weighted_high * captured)
        if not self.spline:  # the affine response: plain sums
            total_low, total_high, cross, right_low, right_high = (term.sum(1, dtype=torch.float64) for term in terms)
            normal = torch.stack([torch.stack([total_low, cross], -1), torch.stack([cross, total_high], -1)], -2)
            return normal, torch.stack([right_low, right_high], -1)
        flat = (index + (torch.arange(batch, device=index.device) * size)[:, None]).flatten()
        stacked = torch.stack(terms, -1).flatten(0, 1).double()
        sums = stacked.new_zeros(batch * size, 5).index_add_(0, flat, stacked).view(batch, size, 5)
        # Per knot i, the sums over the pixels whose pair is (i, i + 1).
        diagonal = sums[..., 0].clone()
        diagonal[:, 1:] += sums[:, :-1, 1]
        right = sums[..., 3].clone()
        right[:, 1:] += sums[:, :-1, 4]
        normal = torch.diag_embed(diagonal)
        off = torch.arange(size - 1, device=index.device)
        normal[:, off, off + 1] = sums[:, :-1, 2]
        normal[:, off + 1, off] = sums[:, :-1, 2]
        return normal, right
