"""ECR on aligned pairs with saturated captured pixels scored as censored (Tobit) observations.

Model (:ref:`model-censored`): each saturated reading's ``log Phi`` term, expanded to second order about each
hypothesis's mode, is a Gaussian pseudo-observation; the log-likelihood ratio is the Gaussian closed form of the
pseudo-observations' sums plus ``(SS_0 - SS_1) / 2 + sum_n (c_1n - c_0n)`` (Laplace's approximation at the mode).

The two hypotheses are the map's response (``1``) and the one mean of unrelated images (``0``);
:mod:`~enmi_torch.scores.censoring` gives each saturated pixel's pseudo-observation ``(pseudo_n, weight_n)`` and
constant ``c_n``, the other pixels keep their reading and weight ``1 / (sigma^2 + tau^2)``. The fit iterates the
expansion to its mode (iteratively reweighted least squares, a Newton step each). ``SS`` is a hypothesis' weighted sum
of squares about its own weighted mean and the Gaussian closed form each response's
(:mod:`~enmi_torch.scores.ecr_statistics`); ECR is ``(LLR - penalty) / n`` as in the Gaussian model. For the binned and
linear responses this is the exact maximised likelihood ratio of the censored model; for the shrunk one, Laplace's
approximation of the integral over the bins' deviations. Without a saturated pixel every pseudo-observation is the
reading, both corrections vanish and ECR is the Gaussian value. The shrunk response's ``delta^2``, when estimated, is
the profile maximum of the pseudo-observations' sums, re-read at each step of the fit. Gradients reach ``captured`` (its
readings that are not saturated) and the variance through the final Newton step (the implicit derivative of the mode);
``tau^2`` and ``delta^2`` are held.
"""

from __future__ import annotations

import torch
from torch import Tensor

from enmi_torch.binning import hard_bin_index
from enmi_torch.scores.censoring import tobit_expansion
from enmi_torch.scores.ecr_model_variance import RESPONSE_VARIANCE_ESTIMATE, check_response_variance
from enmi_torch.scores.ecr_statistics import ecr_from_sums, linear_ecr
from enmi_torch.scores.shrunk_response import bin_positions, shrunk_llr

# The fit stops when no fitted mean moves by more than this fraction of the value range, or after this many steps.
_TOLERANCE, _STEPS = 1e-10, 64


class _Rows:
    """``S`` rows of ``N`` readings over their reference bins: weighted per-bin sums and the fits of each response."""

    def __init__(self, reference: Tensor, valid: Tensor, bins: int, value_range: tuple[float, float], response: str):
        self.rows, self.pixels = valid.shape
        self.valid, self.bins, self.value_range, self.response = valid, bins, value_range, response
        self.reference = reference
        if response != "linear":
            offsets = torch.arange(self.rows, device=valid.device)[:, None] * bins
            self.cells = hard_bin_index(reference, bins, value_range)
            self.flat_cells = (self.cells + offsets).flatten()
            self.count = self._sums(valid)
            self.positions = bin_positions(bins, reference.dtype, reference.device)

    def _sums(self, per_pixel: Tensor) -> Tensor:
        """Per-bin sums ``(S, bins)`` of ``(S, N)`` values."""
        sums = per_pixel.new_zeros(self.rows * self.bins).index_add(0, self.flat_cells, per_pixel.flatten())
        return sums.view(self.rows, self.bins)

    def bin_sums(self, pseudo: Tensor, weight: Tensor, centre: Tensor) -> tuple[Tensor, Tensor]:
        """``W_j`` and ``S_j = sum w (v - centre)`` ``(S, bins)``."""
        return self._sums(weight), self._sums(weight * (pseudo - centre))

    def response_variance(self, pseudo: Tensor, weight: Tensor, centre: Tensor) -> Tensor:
        """The shrunk response's ``delta^2`` ``(S,)``: the profile maximum of these pseudo-observations' sums."""
        total, value = self.bin_sums(pseudo, weight, centre)
        return shrunk_llr(total.T, value.T, self.positions, self.value_range)[1]

    def fitted(self, pseudo: Tensor, weight: Tensor, response_variance: Tensor | None) -> Tensor:
        """The response's weighted fit of ``pseudo`` ``(S, N)`` at every pixel (``None`` variance: one mean)."""
        tiny = torch.finfo(weight.dtype).tiny
        total = weight.sum(1, keepdim=True).clamp_min(tiny)
        mean = (weight * pseudo).sum(1, keepdim=True) / total
        if response_variance is None:
            return mean.expand_as(pseudo)
        if self.response == "linear":
            centred = self.reference - (weight * self.reference).sum(1, keepdim=True) / total
            spread = (weight * centred.square()).sum(1, keepdim=True).clamp_min(tiny)
            slope = ((weight * centred * (pseudo - mean)).sum(1, keepdim=True) / spread).clamp_min(0.0)
            return mean + slope * centred
        weights, values = self.bin_sums(pseudo, weight, mean)
        occupied = weights > 0
        means = torch.where(occupied, values / weights.clamp_min(tiny), 0.0)
        if self.response == "binned":
            return (means + mean).gather(1, self.cells)
        shrink = torch.where(occupied, (1 + response_variance[:, None] * weights).reciprocal(), 1.0)
        pull = torch.where(occupied, shrink * weights, 0.0)
        pulled = pull.sum(1, keepdim=True).clamp_min(tiny)
        centre = (pull * self.positions).sum(1, keepdim=True) / pulled
        level = (pull * means).sum(1, keepdim=True) / pulled
        offset = self.positions - centre
        spread = (pull * offset.square()).sum(1, keepdim=True).clamp_min(tiny)
        slope = ((pull * offset * (means - level)).sum(1, keepdim=True) / spread).clamp_min(0.0)
        line = level + slope * offset
        return (mean + (1 - shrink) * means + shrink * line).gather(1, self.cells)


def _expanded(values, total_variance, side, saturated, fit: Tensor, valid: Tensor):
    """Pseudo-observations, weights and constants ``(S, N)`` at the fitted means ``fit``.

    ``saturated``: the saturated readings' indices (``nonzero(as_tuple=True)``): only they are expanded.
    """
    pseudo, weight, constant = tobit_expansion(
        fit[saturated], total_variance[saturated], values[saturated], side[saturated]
    )
    return (
        values.index_put(saturated, pseudo),
        (valid / total_variance).index_put(saturated, weight),
        torch.zeros_like(fit).index_put(saturated, constant),
    )


def _mode(rows: _Rows, values, total_variance, side, saturated, response_variance, estimate: bool):
    """Pseudo-observations at the mode of one hypothesis, and its ``delta^2`` ``(S,)`` (``None``: one mean)."""
    valid = rows.valid
    fit = rows.fitted(values, valid / total_variance, response_variance)
    scale = rows.value_range[1] - rows.value_range[0]
    with torch.no_grad():
        for _ in range(_STEPS):
            pseudo, weight, _ = _expanded(values, total_variance, side, saturated, fit, valid)
            if estimate:
                centre = (weight * pseudo).sum(1, keepdim=True) / weight.sum(1, keepdim=True)
                response_variance = rows.response_variance(pseudo, weight, centre)
            moved = rows.fitted(pseudo, weight, response_variance)
            settled = bool(((moved - fit).abs() * valid <= _TOLERANCE * scale).all())
            fit = moved
            if settled:
                break
    # One more Newton step from the detached mode carries the mode's implicit derivative in the inputs.
    pseudo, weight, _ = _expanded(values, total_variance, side, saturated, fit.detach(), valid)
    fit = rows.fitted(pseudo, weight, response_variance)
    return (*_expanded(values, total_variance, side, saturated, fit, valid), response_variance)


def _spread(pseudo: Tensor, weight: Tensor) -> Tensor:
    """Weighted sum of squares about the weighted mean, ``(S,)``."""
    mean = (weight * pseudo).sum(1, keepdim=True) / weight.sum(1, keepdim=True).clamp_min(
        torch.finfo(weight.dtype).tiny
    )
    return (weight * (pseudo - mean).square()).sum(1)


def censored_ecr(
    values: Tensor,
    reference: Tensor,
    total_variance: Tensor,
    valid: Tensor,
    side: Tensor,
    bins: int,
    value_range: tuple[float, float],
    response: str,
    response_variance: float | str | Tensor,
) -> tuple[Tensor, Tensor]:
    """ECR ``(S,)`` of ``S`` aligned pairs ``(S, N)`` with saturated readings censored, and the ``delta^2`` it used.

    ``values`` are the readings, ``reference`` the map values under them, ``total_variance`` ``sigma^2 + tau^2``,
    ``valid`` float 0/1, ``side`` ``+1`` / ``-1`` / ``0`` (:func:`~enmi_torch.scores.censoring.saturated_pixels`), all
    ``(S, N)`` float64 where they matter. ``response_variance``: the shrunk response's ``delta^2`` (a number or
    ``(S,)``) or ``"estimate"``; the other responses return 0 for it.
    """
    saturated = ((side != 0) & (valid > 0)).nonzero(as_tuple=True)
    rows = _Rows(reference, valid, bins, value_range, response)
    estimate = response == "shrunk" and isinstance(response_variance, str)
    if response == "shrunk":
        if estimate:
            response_variance = RESPONSE_VARIANCE_ESTIMATE
            start = torch.full((rows.rows,), float("inf"), dtype=values.dtype, device=values.device)
        else:
            start = torch.as_tensor(response_variance, dtype=values.dtype, device=values.device).expand(rows.rows)
    else:
        start = torch.full((rows.rows,), float("inf"), dtype=values.dtype, device=values.device)
    null_pseudo, null_weight, null_constant, _ = _mode(rows, values, total_variance, side, saturated, None, False)
    pseudo, weight, constant, delta2 = _mode(rows, values, total_variance, side, saturated, start, estimate)
    count = valid.sum(1)
    if response == "linear":
        gaussian = linear_ecr(
            pseudo, reference[None], weight.clamp_min(torch.finfo(weight.dtype).tiny).reciprocal(), valid
        )[0]
        delta2 = torch.zeros_like(count)
    else:
        centre = (weight * pseudo).sum(1, keepdim=True) / weight.sum(1, keepdim=True)
        weights, sums = rows.bin_sums(pseudo, weight, centre)
        shrunk = None
        if response == "shrunk":
            delta2 = delta2.detach()
            shrunk = (rows.positions, value_range, delta2)
        else:
            delta2 = torch.zeros_like(count)
        gaussian = ecr_from_sums(rows.count, weights, sums, -1, shrunk=shrunk)
    correction = 0.5 * (_spread(null_pseudo, null_weight) - _spread(pseudo, weight)) + (constant - null_constant).sum(1)
    return torch.where(count > 0.5, gaussian + correction / count.clamp_min(1), 0.0), delta2


def aligned_censored_ecr(
    captured, reference, total_variance, valid, side, inputs, response, response_variance
) -> Tensor:
    """:func:`~enmi_torch.scores.ecr.ecr` ``(C, B)`` of its checked inputs, saturated readings censored.

    ``captured`` ``(B, N)``, ``reference`` ``(C, B, N)``, ``total_variance`` and ``valid`` broadcast to it, float64;
    ``side`` ``(C B, N)``: :func:`censored_ecr` row by row.
    """
    shape, pixels = reference.shape, reference.shape[-1]
    rows = [
        part.expand(shape).reshape(-1, pixels)
        for part in (captured, reference, total_variance, torch.ones_like(captured) if valid is None else valid)
    ]
    delta2 = check_response_variance(response_variance)
    score, _ = censored_ecr(*rows, side, inputs.bins, inputs.value_range, response, delta2)
    return score.view(shape[:-1])


def aligned_censored_response_variance(inputs, tau2, side: Tensor) -> Tensor:
    """The shrunk response's ``delta^2`` ``(C, B)`` with the saturated readings censored, at ``tau2`` ``(C, B)``."""
    with torch.no_grad():
        captured, reference, noise = (
            part.detach().to(torch.float64) for part in (inputs.captured, inputs.reference, inputs.variance)
        )
        tau2 = torch.as_tensor(tau2, dtype=torch.float64, device=captured.device)
        total = noise + (tau2 if tau2.dim() == reference.dim() else tau2.expand(reference.shape[:-1])[..., None])
        valid = None if inputs.pair_weight is None else inputs.pair_weight.detach().to(torch.float64)
        shape, pixels = reference.shape, reference.shape[-1]
        rows = [
            part.expand(shape).reshape(-1, pixels)
            for part in (captured, reference, total, torch.ones_like(captured) if valid is None else valid)
        ]
        _, delta2 = censored_ecr(*rows, side, inputs.bins, inputs.value_range, "shrunk", RESPONSE_VARIANCE_ESTIMATE)
    return delta2.view(shape[:-1])
